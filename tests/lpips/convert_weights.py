#!/usr/bin/env python3
"""Converts the `lpips` package's pretrained networks to the safetensors files `pipeline`
reads (`eval.lpips_weights`).

    pip install lpips torch torchvision
    python tests/lpips/convert_weights.py --net vgg --output lpips_vgg.safetensors
    python tests/lpips/convert_weights.py --net alex --output lpips_alex.safetensors

The trunk weights come from torchvision's ImageNet checkpoints (downloaded by torchvision on
first use), the lin layers from the `lpips` package (v0.1). The file holds the module's whole
`state_dict()` in f32, under the package's own names.
"""
import argparse

import numpy as np


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--net", choices=["vgg", "alex"], required=True)
    parser.add_argument("--output", required=True)
    args = parser.parse_args()

    import lpips  # noqa: E402  (imported late so --help works without torch)

    from safetensors_io import write_safetensors

    model = lpips.LPIPS(net=args.net, version="0.1", verbose=False)
    tensors = {
        name: value.detach().cpu().numpy().astype(np.float32)
        for name, value in model.state_dict().items()
    }
    write_safetensors(args.output, tensors, {"source": f"lpips {lpips.__version__ if hasattr(lpips, '__version__') else ''} net={args.net} version=0.1"})
    print(f"wrote {len(tensors)} tensors to {args.output}")


if __name__ == "__main__":
    main()
