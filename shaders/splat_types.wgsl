// The camera uniform of every splat kernel (binding 0 of splat_project.wgsl,
// splat_rasterize.wgsl and splat_rasterize_backward.wgsl), included by them with
// `//#include "splat_types.wgsl"` (src/compute/src/backend/shaders.rs). Its Rust twin is
// `CameraUniform` in src/compute/src/splat/gpu/mod.rs; a test checks the two layouts agree.

struct SplatCamera {
    // Rows of the world-to-camera rotation; w holds the translation component.
    rotation0: vec4<f32>,
    rotation1: vec4<f32>,
    rotation2: vec4<f32>,
    // fx, fy, cx, cy (continuous pixels).
    intrinsics: vec4<f32>,
    // Camera centre in world coordinates (w unused).
    center: vec4<f32>,
    background: vec4<f32>,
    // width, height, tiles_x, tiles_y.
    image: vec4<u32>,
    // gaussians, sh coefficients per channel, first tile row, end tile row (exclusive).
    counts: vec4<u32>,
    // smooth cutoff (0/1), alpha gradient given (0/1), depth gradient given (0/1), unused.
    flags: vec4<u32>,
}
