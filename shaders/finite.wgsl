// Whether an f32 is finite (neither infinite nor NaN), included by kernels with
// `//#include "finite.wgsl"` (src/compute/src/backend/shaders.rs). A bit test on the
// exponent (all ones for infinities and NaNs), because WGSL lets compilers assume floats are
// finite, so `x == x` or `x != x` may fold away.

fn finite(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7f800000u) != 0x7f800000u;
}
