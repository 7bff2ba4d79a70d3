// The uniform block of every LPIPS kernel (binding 0 of lpips_forward.wgsl and
// lpips_backward.wgsl; each entry point's comment says how it reads the fields) and the
// helpers both files use, included by them with `//#include "lpips_types.wgsl"`
// (src/compute/src/backend/shaders.rs). Its Rust twin is `Params` in
// src/compute/src/lpips/gpu.rs; a test checks the two layouts agree.

struct LpipsParams {
    images: u32,
    in_channels: u32,
    in_height: u32,
    in_width: u32,
    out_channels: u32,
    out_height: u32,
    out_width: u32,
    kernel: u32,
    stride: u32,
    padding: u32,
    total: u32,
    _pad: u32,
}

// `a s - b t`, exactly 0 when `a = b` and `s = t`. Written plainly, a compiler may contract
// it into `fma(a, s, -(b t))`, which leaves the rounding error of `b t` (NVIDIA does): the
// distance of two identical images (or its gradient) would then not be exactly 0.
fn normalised_difference(a: f32, s: f32, b: f32, t: f32) -> f32 {
    return select(a * s - b * t, 0.0, a == b && s == t);
}
