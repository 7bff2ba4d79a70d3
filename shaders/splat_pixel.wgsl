// Pixel tests shared by the forward and backward rasterize kernels (splat_rasterize.wgsl,
// splat_rasterize_backward.wgsl), included with `//#include "splat_pixel.wgsl"`
// (src/compute/src/backend/shaders.rs). The including kernel declares
// `const ALPHA_THRESHOLD: f32`.

// Brush's C1 cutoff (tests only), s(u) = 3u^2 - 2u^3 with u = clamp((alpha - t) / t, 0, 1),
// and its derivative ds/dalpha: `vec2(s, ds/dalpha)`.
fn smooth_step(alpha: f32) -> vec2<f32> {
    let u = clamp((alpha - ALPHA_THRESHOLD) / ALPHA_THRESHOLD, 0.0, 1.0);
    return vec2<f32>(u * u * (3.0 - 2.0 * u), 6.0 * u * (1.0 - u) / ALPHA_THRESHOLD);
}

// Whether the pixel lies in [floor(m - r - 1), ceil(m + r + 1)) on both axes.
fn in_box(pixel: vec2<f32>, mean: vec2<f32>, radius: vec2<f32>) -> bool {
    let low = floor(mean - radius - 1.0);
    let high = ceil(mean + radius + 1.0);
    return all(pixel >= low) && all(pixel < high);
}
