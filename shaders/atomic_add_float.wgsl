// Native f32 atomic add on the gradient buffer (wgpu SHADER_FLOAT32_ATOMIC). This file
// replaces the atomic-add region (between its begin and end marker lines) of kernels that
// accumulate gradients; the binding number and the function signature must match
// atomic_add_cas.wgsl.

@group(0) @binding(15) var<storage, read_write> gradients: array<atomic<f32>>;

fn gradient_add(index: u32, value: f32) {
    if value != 0.0 {
        atomicAdd(&gradients[index], value);
    }
}
