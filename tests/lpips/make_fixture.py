#!/usr/bin/env python3
"""Writes tests/lpips/fixture.safetensors: LPIPS values computed by the `lpips` Python package
(v0.1, the real VGG16 and AlexNet architectures) with seeded random weights, plus PSNR and
SSIM computed with torch, on small fixed image pairs. The Rust test
(stages/eval/src/lpips/tests.rs) regenerates the same weights from the same seed and must
match within 1e-4.

    python -m venv venv && venv/bin/pip install lpips torch torchvision numpy
    venv/bin/python tests/lpips/make_fixture.py

The weights (14.7 M VGG16 parameters) are not stored: both sides derive them with the
counter-based splitmix64 generator below (stages/eval/src/lpips/seeded.rs is its twin); the
fixture stores per-tensor checksums so a generator mismatch is reported as such.
"""
import math
import os

import numpy as np
import torch
import torch.nn.functional as F

import lpips

from safetensors_io import write_safetensors

SEED = 20250601
HEIGHT, WIDTH = 40, 56
MASK64 = (1 << 64) - 1
GAMMA = 0x9E3779B97F4A7C15


def mix64_int(z):
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & MASK64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & MASK64
    return z ^ (z >> 31)


def mix64_array(z):
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def fnv1a64(text):
    value = 0xCBF29CE484222325
    for byte in text.encode():
        value = ((value ^ byte) * 0x100000001B3) & MASK64
    return value


def uniforms(seed, name, count):
    """`count` exact uniforms in [0, 1): element i is mix64(stream + (i + 1) * GAMMA) >> 40."""
    stream = np.uint64(mix64_int(seed ^ fnv1a64(name)))
    index = np.arange(1, count + 1, dtype=np.uint64)
    with np.errstate(over="ignore"):
        bits = mix64_array(stream + index * np.uint64(GAMMA))
    return (bits >> np.uint64(40)).astype(np.float64) / 16777216.0


def seeded_state(model, seed):
    """Seeded weights for every conv and lin tensor, in the Rust order (trunk convs weight
    then bias, then lin0..lin4). Returns the ordered (name, float32 array) list."""
    state = model.state_dict()
    conv_names = [n for n in state if n.startswith("net.") and n.endswith(".weight")]
    ordered = []
    for weight_name in conv_names:
        weight = state[weight_name]
        out_channels, in_channels, kh, kw = weight.shape
        fan_in = in_channels * kh * kw
        u = uniforms(seed, weight_name, weight.numel())
        ordered.append((weight_name, ((2.0 * u - 1.0) * math.sqrt(6.0 / fan_in)).astype(np.float32).reshape(weight.shape)))
        bias_name = weight_name[: -len("weight")] + "bias"
        u = uniforms(seed, bias_name, out_channels)
        ordered.append((bias_name, ((2.0 * u - 1.0) * (1.0 / math.sqrt(fan_in))).astype(np.float32)))
    for layer in range(5):
        name = f"lin{layer}.model.1.weight"
        shape = state[name].shape
        channels = shape[1]
        u = uniforms(seed, name, channels)
        ordered.append((name, (u * math.sqrt(6.0 / channels)).astype(np.float32).reshape(shape)))
    with torch.no_grad():
        for name, values in ordered:
            state[name].copy_(torch.from_numpy(values))
    return ordered


def checksums(ordered):
    rows = []
    for _, values in ordered:
        flat = values.astype(np.float64).ravel()
        rows.append([math.fsum(flat), math.fsum(flat * flat), flat[0], flat[-1]])
    return np.array(rows, dtype=np.float64)


def make_images():
    rng = np.random.default_rng(7)
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH]
    smooth = np.stack(
        [
            0.5 + 0.4 * np.sin(x / 6.0 + y / 9.0),
            0.5 + 0.4 * np.cos(x / 11.0 - y / 5.0),
            0.5 + 0.3 * np.sin((x + y) / 7.0),
        ],
        axis=-1,
    )
    first, second = [], []
    # Pair 0: independent noise images.
    first.append(rng.random((HEIGHT, WIDTH, 3)))
    second.append(rng.random((HEIGHT, WIDTH, 3)))
    # Pair 1: a smooth image and a noisy copy.
    first.append(smooth)
    second.append(np.clip(smooth + rng.normal(0.0, 0.08, smooth.shape), 0.0, 1.0))
    # Pair 2: a smooth image with a dark square and the same shifted by two pixels.
    blocky = smooth.copy()
    blocky[10:25, 14:30] *= 0.2
    first.append(blocky)
    second.append(np.roll(blocky, 2, axis=1))
    to_u8 = lambda images: np.round(np.clip(np.stack(images), 0.0, 1.0) * 255.0).astype(np.uint8)
    return to_u8(first), to_u8(second)


def to_lpips_input(images_u8):
    """uint8 (N, H, W, 3) -> float32 NCHW in [-1, 1], the same f32 operations as the Rust."""
    values = images_u8.astype(np.float32) / np.float32(255.0)
    values = values * np.float32(2.0) - np.float32(1.0)
    return torch.from_numpy(np.ascontiguousarray(values.transpose(0, 3, 1, 2)))


def ssim_3dgs(first, second):
    """The 3DGS / GauHuman ssim(): 11 px Gaussian window, sigma 1.5, zero padding, mean, f64."""
    coords = torch.arange(11, dtype=torch.float64) - 5
    gauss = torch.exp(-(coords**2) / (2 * 1.5**2))
    gauss = gauss / gauss.sum()
    window = (gauss[:, None] @ gauss[None, :]).expand(3, 1, 11, 11).contiguous()
    conv = lambda image: F.conv2d(image, window, padding=5, groups=3)
    mu1, mu2 = conv(first), conv(second)
    sigma1 = conv(first * first) - mu1 * mu1
    sigma2 = conv(second * second) - mu2 * mu2
    sigma12 = conv(first * second) - mu1 * mu2
    c1, c2 = 0.01**2, 0.03**2
    ssim_map = ((2 * mu1 * mu2 + c1) * (2 * sigma12 + c2)) / ((mu1**2 + mu2**2 + c1) * (sigma1 + sigma2 + c2))
    return ssim_map.mean(dim=(1, 2, 3))


def main():
    torch.manual_seed(0)
    first, second = make_images()
    tensors = {"in0": first, "in1": second}
    in0, in1 = to_lpips_input(first), to_lpips_input(second)
    for net in ["alex", "vgg"]:
        model = lpips.LPIPS(pretrained=False, net=net, version="0.1", pnet_rand=True, verbose=False).eval()
        ordered = seeded_state(model, SEED)
        with torch.no_grad():
            total, layers = model(in0, in1, retPerLayer=True)
        tensors[f"lpips.{net}"] = total.reshape(-1).numpy().astype(np.float64)
        tensors[f"lpips.{net}.layers"] = torch.stack([layer.reshape(-1) for layer in layers], dim=1).numpy().astype(np.float64)
        tensors[f"checksum.{net}"] = checksums(ordered)
        print(net, tensors[f"lpips.{net}"], "layers", tensors[f"lpips.{net}.layers"])
    float0 = torch.from_numpy(first.astype(np.float64) / 255.0).permute(0, 3, 1, 2)
    float1 = torch.from_numpy(second.astype(np.float64) / 255.0).permute(0, 3, 1, 2)
    mse = ((float0 - float1) ** 2).mean(dim=(1, 2, 3))
    tensors["psnr"] = (-10.0 * torch.log10(mse)).numpy()
    tensors["ssim"] = ssim_3dgs(float0, float1).numpy()
    print("psnr", tensors["psnr"], "ssim", tensors["ssim"])
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "fixture.safetensors")
    write_safetensors(
        path,
        tensors,
        {
            "seed": SEED,
            "generator": "tests/lpips/make_fixture.py",
            "lpips": "lpips 0.1.4 LPIPS(version='0.1'), inputs uint8/255*2-1",
            "torch": torch.__version__,
        },
    )
    print(f"wrote {path} ({os.path.getsize(path)} bytes)")


if __name__ == "__main__":
    main()
