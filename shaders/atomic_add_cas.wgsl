// Portable f32 atomic add on the gradient buffer: a compare-exchange loop on the bit
// pattern held in an atomic<u32>. Kernels that accumulate gradients include this header,
// `//#include "atomic_add_cas.wgsl"`, alone between the atomic-add begin and end marker
// lines; the host swaps in atomic_add_float.wgsl when the adapter has native f32 atomics.

@group(0) @binding(15) var<storage, read_write> gradients: array<atomic<u32>>;

fn gradient_add(index: u32, value: f32) {
    if value == 0.0 {
        return;
    }
    var old = atomicLoad(&gradients[index]);
    loop {
        let new_bits = bitcast<u32>(bitcast<f32>(old) + value);
        let result = atomicCompareExchangeWeak(&gradients[index], old, new_bits);
        if result.exchanged {
            break;
        }
        old = result.old_value;
    }
}
