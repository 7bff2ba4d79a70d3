// The uniform block of every LPIPS kernel (binding 0 of lpips_forward.wgsl and
// lpips_backward.wgsl; each entry point's comment says how it reads the fields), included
// by them with `//#include "lpips_types.wgsl"` (src/compute/src/backend/shaders.rs). Its
// Rust twin is `Params` in src/compute/src/lpips/gpu.rs; a test checks the two layouts agree.

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
