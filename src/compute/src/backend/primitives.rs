//! Generic GPU building blocks: an exclusive prefix sum and a stable key-value radix sort,
//! both recorded into a caller's command encoder so data stays on the GPU.

use std::borrow::Cow;

use super::{BackendError, GpuBuffer, GpuContext, KernelSource};

const BLOCK: u32 = 256;
const DIGIT_BITS: u32 = 4;
const DIGITS: u32 = 1 << DIGIT_BITS;

const SCAN_WGSL: &str = include_str!("../../../../shaders/scan_exclusive.wgsl");
const SORT_WGSL: &str = include_str!("../../../../shaders/sort_radix.wgsl");

fn source(name: &'static str, wgsl: &'static str, entry_point: &'static str) -> KernelSource {
    KernelSource {
        name,
        wgsl: Cow::Borrowed(wgsl),
        entry_point,
    }
}

/// `ScanParams` in `scan_exclusive.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct ScanParams {
    count: u32,
    pad: [u32; 3],
}

/// `SortParams` in `sort_radix.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct SortParams {
    count: u32,
    shift: u32,
    blocks: u32,
    pad: u32,
}

/// This module's uniform structs for the layout test in [`super::shaders`].
#[cfg(test)]
pub(crate) fn wgsl_twins() -> Vec<super::shaders::WgslTwin> {
    use super::shaders::wgsl_twin;
    vec![
        wgsl_twin!(ScanParams as "ScanParams" in ["scan_exclusive.wgsl"] {
            "count" => count,
            "_pad0" => pad[0],
            "_pad1" => pad[1],
            "_pad2" => pad[2],
        }),
        wgsl_twin!(SortParams as "SortParams" in ["sort_radix.wgsl"] {
            "count" => count,
            "shift" => shift,
            "blocks" => blocks,
            "_pad" => pad,
        }),
    ]
}

/// Records an in-place exclusive prefix sum of the first `count` u32 of `data`. Returns a
/// buffer whose first element is the total of all `count` values.
pub fn exclusive_scan(
    context: &GpuContext,
    encoder: &mut wgpu::CommandEncoder,
    data: &wgpu::Buffer,
    count: u32,
) -> Result<GpuBuffer, BackendError> {
    let blocks = count.div_ceil(BLOCK).max(1);
    let block_sums = context.zeros("scan block sums", blocks as usize, 4)?;
    let params = context.uniform("scan params", &ScanParams { count, pad: [0; 3] });
    let scan = context.kernel(&source("scan_blocks", SCAN_WGSL, "scan_blocks"))?;
    let add = context.kernel(&source("scan_add", SCAN_WGSL, "scan_add"))?;
    let bindings = [(0, &params), (1, data), (2, &block_sums.buffer)];
    if count == 0 {
        return Ok(block_sums);
    }
    context.dispatch(encoder, &scan, &bindings, blocks);
    if blocks == 1 {
        return Ok(block_sums);
    }
    let total = exclusive_scan(context, encoder, &block_sums.buffer, blocks)?;
    context.dispatch(encoder, &add, &bindings, blocks);
    Ok(total)
}

/// Records a stable sort of `count` pairs by the low `key_bits` bits of their keys.
/// Consumes the buffers and returns the sorted `(keys, values)` (possibly the same buffers).
pub fn radix_sort(
    context: &GpuContext,
    encoder: &mut wgpu::CommandEncoder,
    keys: GpuBuffer,
    values: GpuBuffer,
    count: u32,
    key_bits: u32,
) -> Result<(GpuBuffer, GpuBuffer), BackendError> {
    let passes = key_bits.min(32).div_ceil(DIGIT_BITS);
    if count <= 1 || passes == 0 {
        return Ok((keys, values));
    }
    let blocks = count.div_ceil(BLOCK);
    let counts = context.zeros("sort counts", (blocks * DIGITS) as usize, 4)?;
    let mut keys_other = context.zeros("sort keys", count as usize, 4)?;
    let mut values_other = context.zeros("sort values", count as usize, 4)?;
    let count_kernel = context.kernel(&source("sort_count", SORT_WGSL, "sort_count"))?;
    let scatter_kernel = context.kernel(&source("sort_scatter", SORT_WGSL, "sort_scatter"))?;
    let (mut keys, mut values) = (keys, values);
    for pass in 0..passes {
        let params = context.uniform(
            "sort params",
            &SortParams {
                count,
                shift: pass * DIGIT_BITS,
                blocks,
                pad: 0,
            },
        );
        let bindings = [
            (0, &params),
            (1, &keys.buffer),
            (2, &values.buffer),
            (3, &counts.buffer),
            (4, &keys_other.buffer),
            (5, &values_other.buffer),
        ];
        context.dispatch(
            encoder,
            &count_kernel,
            &[bindings[0], bindings[1], bindings[3]],
            blocks,
        );
        exclusive_scan(context, encoder, &counts.buffer, blocks * DIGITS)?;
        context.dispatch(encoder, &scatter_kernel, &bindings, blocks);
        std::mem::swap(&mut keys, &mut keys_other);
        std::mem::swap(&mut values, &mut values_other);
    }
    keys.len = count as usize;
    values.len = count as usize;
    Ok((keys, values))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::test_support::gpu_test_context;

    /// A small deterministic generator (xorshift) so tests need no extra crate.
    fn pseudo_random(seed: u64, count: usize) -> Vec<u32> {
        let mut state = seed.max(1);
        (0..count)
            .map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                (state >> 32) as u32
            })
            .collect()
    }

    fn check_scan(values: &[u32]) {
        let Some(context) = gpu_test_context() else {
            return;
        };
        check_scan_on(&context, values);
    }

    fn check_scan_on(context: &GpuContext, values: &[u32]) {
        let buffer = context.upload("scan input", values).unwrap();
        let mut encoder = context.encoder();
        let total =
            exclusive_scan(context, &mut encoder, &buffer.buffer, values.len() as u32).unwrap();
        context.submit_and_wait(encoder).unwrap();
        let scanned: Vec<u32> = context
            .download(context.encoder(), &buffer.buffer, values.len())
            .unwrap();
        let total: Vec<u32> = context
            .download(context.encoder(), &total.buffer, 1)
            .unwrap();
        let mut expected = Vec::with_capacity(values.len());
        let mut running = 0_u32;
        for value in values {
            expected.push(running);
            running = running.wrapping_add(*value);
        }
        assert_eq!(scanned, expected, "scan of {} values", values.len());
        assert_eq!(total[0], running, "total of {} values", values.len());
    }

    #[test]
    fn exclusive_scan_matches_a_cpu_prefix_sum() {
        check_scan(&[]);
        check_scan(&[7]);
        check_scan(&[1; 256]);
        check_scan(&[3; 257]);
        let random: Vec<u32> = pseudo_random(3, 70_000).iter().map(|x| x % 100).collect();
        check_scan(&random);
    }

    fn check_sort(keys: &[u32], key_bits: u32) {
        let Some(context) = gpu_test_context() else {
            return;
        };
        check_sort_on(&context, keys, key_bits);
    }

    fn check_sort_on(context: &GpuContext, keys: &[u32], key_bits: u32) {
        let values: Vec<u32> = (0..keys.len() as u32).collect();
        let mut encoder = context.encoder();
        let (sorted_keys, sorted_values) = radix_sort(
            context,
            &mut encoder,
            context.upload("keys", keys).unwrap(),
            context.upload("values", &values).unwrap(),
            keys.len() as u32,
            key_bits,
        )
        .unwrap();
        let mut pending = context
            .download_many::<u32>(
                &mut encoder,
                &[
                    (&sorted_keys.buffer, keys.len()),
                    (&sorted_values.buffer, keys.len()),
                ],
            )
            .unwrap();
        context.finish_downloads(encoder, &mut pending).unwrap();
        // A stable CPU sort by the same bits is the reference.
        let mask = if key_bits >= 32 {
            u32::MAX
        } else {
            (1_u32 << key_bits) - 1
        };
        let mut expected: Vec<(u32, u32)> = keys.iter().copied().zip(values).collect();
        expected.sort_by_key(|(key, _)| key & mask);
        let expected_keys: Vec<u32> = expected.iter().map(|pair| pair.0).collect();
        let expected_values: Vec<u32> = expected.iter().map(|pair| pair.1).collect();
        assert_eq!(
            pending[0].values,
            expected_keys,
            "keys ({} pairs)",
            keys.len()
        );
        assert_eq!(
            pending[1].values,
            expected_values,
            "values ({} pairs)",
            keys.len()
        );
    }

    #[test]
    fn radix_sort_matches_a_stable_cpu_sort() {
        check_sort(&[], 32);
        check_sort(&[5], 32);
        check_sort(&[3, 1, 2, 1, 3, 0], 2);
        // Many ties exercise stability; the full 32 bits exercise the top digit.
        let small: Vec<u32> = pseudo_random(11, 5_000).iter().map(|x| x % 37).collect();
        check_sort(&small, 6);
        check_sort(&pseudo_random(5, 40_000), 32);
        let floats: Vec<u32> = pseudo_random(9, 3_000)
            .iter()
            .map(|x| (0.01 + (*x as f32) / 1e6).to_bits())
            .chain([u32::MAX; 40])
            .collect();
        check_sort(&floats, 32);
    }

    #[test]
    fn radix_sort_with_fewer_bits_leaves_high_bits_unsorted_but_stable() {
        let keys: Vec<u32> = pseudo_random(21, 1_000);
        check_sort(&keys, 8);
    }

    #[test]
    fn scan_and_sort_on_two_dimensional_grids_match_the_cpu() {
        let Some(context) = crate::backend::test_support::gpu_test_context_with_dispatch_limit(2)
        else {
            return;
        };
        let values: Vec<u32> = pseudo_random(4, 3_000).iter().map(|x| x % 50).collect();
        check_scan_on(&context, &values);
        check_sort_on(&context, &pseudo_random(6, 2_000), 32);
    }
}
