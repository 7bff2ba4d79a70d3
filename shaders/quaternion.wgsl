// Rotation matrices of `w x y z` quaternions (a vec4 holds w in .x) and their backward, as
// core::rotation::quat_wxyz_to_matrix and src/avatar/src/skinning.rs
// quat_matrix_backward, included by kernels with `//#include "quaternion.wgsl"`
// (src/compute/src/backend/shaders.rs). The including kernel also includes "finite.wgsl".
// WGSL matrices are column-major: `m[c][r]` is row r, column c.

// Below this squared norm (or a non-finite one) a quaternion is degenerate: its rotation is
// the identity and its gradient zero (core::rotation).
fn quat_degenerate(q: vec4<f32>) -> bool {
    let n2 = dot(q, q);
    return !(finite(n2) && n2 > 1e-24);
}

// R(q / |q|); the identity for a degenerate quaternion.
fn quat_matrix(q: vec4<f32>) -> mat3x3<f32> {
    if quat_degenerate(q) {
        return mat3x3<f32>(vec3<f32>(1.0, 0.0, 0.0), vec3<f32>(0.0, 1.0, 0.0), vec3<f32>(0.0, 0.0, 1.0));
    }
    let u = q / sqrt(dot(q, q));
    let w = u.x;
    let x = u.y;
    let y = u.z;
    let z = u.w;
    // Columns of the standard unit-quaternion matrix.
    return mat3x3<f32>(
        vec3<f32>(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y)),
        vec3<f32>(2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x)),
        vec3<f32>(2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)),
    );
}

// The gradient of R(q / |q|) with respect to q given g = dL/dR; zero for a degenerate
// quaternion.
fn quat_matrix_backward(q: vec4<f32>, g: mat3x3<f32>) -> vec4<f32> {
    if quat_degenerate(q) {
        return vec4<f32>(0.0);
    }
    let norm = sqrt(dot(q, q));
    let u = q / norm;
    let w = u.x;
    let x = u.y;
    let y = u.z;
    let z = u.w;
    // g[c][r] is dL/dR of row r, column c.
    let dw = 2.0 * (-z * g[1][0] + y * g[2][0] + z * g[0][1] - x * g[2][1] - y * g[0][2]
        + x * g[1][2]);
    let dx = 2.0 * (y * g[1][0] + z * g[2][0] + y * g[0][1] - 2.0 * x * g[1][1] - w * g[2][1]
        + z * g[0][2] + w * g[1][2] - 2.0 * x * g[2][2]);
    let dy = 2.0 * (-2.0 * y * g[0][0] + x * g[1][0] + w * g[2][0] + x * g[0][1] + z * g[2][1]
        - w * g[0][2] + z * g[1][2] - 2.0 * y * g[2][2]);
    let dz = 2.0 * (-2.0 * z * g[0][0] - w * g[1][0] + x * g[2][0] + w * g[0][1]
        - 2.0 * z * g[1][1] + y * g[2][1] + x * g[0][2] + y * g[1][2]);
    let gn = vec4<f32>(dw, dx, dy, dz);
    return (gn - u * dot(gn, u)) / norm;
}
