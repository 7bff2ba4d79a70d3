//! Generic GPU building blocks: an exclusive prefix sum and a stable key-value radix sort,
//! both recorded into a caller's command encoder so data stays on the GPU.

use super::{BackendError, GpuBuffer, GpuContext};

const BLOCK: u32 = 256;
const DIGIT_BITS: u32 = 4;
const DIGITS: u32 = 1 << DIGIT_BITS;

const SCAN_WGSL: &str = include_str!("../../../../shaders/scan_exclusive.wgsl");
const SORT_WGSL: &str = include_str!("../../../../shaders/sort_radix.wgsl");

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
pub(crate) fn wgsl_twins() -> Vec<super::shaders::tests::WgslTwin> {
    use super::shaders::tests::wgsl_twin;
    vec![
        wgsl_twin!(ScanParams as "ScanParams" in ["scan_exclusive.wgsl"] {
            count, pad[0] as "_pad0", pad[1] as "_pad1", pad[2] as "_pad2",
        }),
        wgsl_twin!(SortParams as "SortParams" in ["sort_radix.wgsl"] {
            count, shift, blocks, pad as "_pad",
        }),
    ]
}

/// An exclusive prefix sum recorded from buffers allocated once for up to `capacity` values:
/// the per-level block sums and their parameter uniforms. Recording a count other than the
/// last one rewrites the parameters of the levels it uses (a few bytes, only on a change), so
/// a steady-state caller uploads nothing.
pub struct ScanWorkspace {
    capacity: u32,
    /// Per level: its parameter uniform and the block sums it writes.
    levels: Vec<(wgpu::Buffer, GpuBuffer)>,
    /// The count each level's uniform holds now.
    written: Vec<u32>,
    /// The level whose block sums hold the total of the last recorded scan.
    total_level: usize,
}

impl ScanWorkspace {
    /// Allocates the levels for scans of up to `capacity` values.
    pub fn new(context: &GpuContext, capacity: u32) -> Result<Self, BackendError> {
        let mut levels = Vec::new();
        let mut written = Vec::new();
        let mut count = capacity;
        loop {
            let blocks = count.div_ceil(BLOCK).max(1);
            let params = context.uniform("scan params", &ScanParams { count, pad: [0; 3] });
            levels.push((
                params,
                context.zeros("scan block sums", blocks as usize, 4)?,
            ));
            written.push(count);
            if blocks == 1 {
                break;
            }
            count = blocks;
        }
        Ok(Self {
            capacity,
            levels,
            written,
            total_level: 0,
        })
    }

    /// The most values one scan may hold.
    pub fn capacity(&self) -> u32 {
        self.capacity
    }

    /// Records an in-place exclusive prefix sum of the first `count` u32 of `data`;
    /// afterwards [`ScanWorkspace::total`] holds their total at element 0.
    pub fn record(
        &mut self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        data: &wgpu::Buffer,
        count: u32,
    ) -> Result<(), BackendError> {
        if count > self.capacity {
            return Err(BackendError::Gpu {
                message: format!(
                    "scan of {count} values in a workspace for {}",
                    self.capacity
                ),
            });
        }
        if count == 0 {
            encoder.clear_buffer(&self.levels[0].1.buffer, 0, None);
            self.total_level = 0;
            return Ok(());
        }
        let scan = context.static_kernel("scan_blocks", SCAN_WGSL, "scan_blocks")?;
        let add = context.static_kernel("scan_add", SCAN_WGSL, "scan_add")?;
        // Down: scan each level's blocks, whose totals the next level scans.
        let mut level = 0;
        let mut level_count = count;
        loop {
            if self.written[level] != level_count {
                context.write(
                    &self.levels[level].0,
                    0,
                    &[ScanParams {
                        count: level_count,
                        pad: [0; 3],
                    }],
                )?;
                self.written[level] = level_count;
            }
            let input = if level == 0 {
                data
            } else {
                &self.levels[level - 1].1.buffer
            };
            let blocks = level_count.div_ceil(BLOCK);
            context.dispatch(
                encoder,
                &scan,
                &[
                    (0, &self.levels[level].0),
                    (1, input),
                    (2, &self.levels[level].1.buffer),
                ],
                blocks,
            );
            if blocks == 1 {
                break;
            }
            level += 1;
            level_count = blocks;
        }
        self.total_level = level;
        // Up: add each level's scanned block totals back to the level below.
        for below in (0..level).rev() {
            let input = if below == 0 {
                data
            } else {
                &self.levels[below - 1].1.buffer
            };
            context.dispatch(
                encoder,
                &add,
                &[
                    (0, &self.levels[below].0),
                    (1, input),
                    (2, &self.levels[below].1.buffer),
                ],
                self.written[below].div_ceil(BLOCK),
            );
        }
        Ok(())
    }

    /// The buffer whose first element is the total of the last recorded scan.
    pub fn total(&self) -> &GpuBuffer {
        &self.levels[self.total_level].1
    }
}

/// A stable key-value radix sort recorded from buffers allocated once for up to `capacity`
/// pairs: the digit histograms, their scan, the ping-pong scratch and one parameter uniform
/// per pass. The caller's `keys` and `values` and the scratch alternate as pass inputs, so the
/// sorted pairs end in the caller's buffers after an even number of passes and in the scratch
/// ([`SortWorkspace::scratch_keys`], [`SortWorkspace::scratch_values`]) after an odd one.
pub struct SortWorkspace {
    capacity: u32,
    counts: GpuBuffer,
    keys: GpuBuffer,
    values: GpuBuffer,
    params: Vec<wgpu::Buffer>,
    written_count: u32,
    scan: ScanWorkspace,
}

/// Passes of 4 bits that cover 32-bit keys.
const MAX_PASSES: u32 = 32 / DIGIT_BITS;

impl SortWorkspace {
    /// Allocates a sort of up to `capacity` pairs.
    pub fn new(context: &GpuContext, capacity: u32) -> Result<Self, BackendError> {
        let blocks = capacity.div_ceil(BLOCK).max(1);
        let params = (0..MAX_PASSES)
            .map(|pass| {
                context.uniform(
                    "sort params",
                    &SortParams {
                        count: capacity,
                        shift: pass * DIGIT_BITS,
                        blocks,
                        pad: 0,
                    },
                )
            })
            .collect();
        Ok(Self {
            capacity,
            counts: context.zeros("sort counts", (blocks * DIGITS) as usize, 4)?,
            keys: context.zeros("sort keys", capacity as usize, 4)?,
            values: context.zeros("sort values", capacity as usize, 4)?,
            params,
            written_count: capacity,
            scan: ScanWorkspace::new(context, blocks * DIGITS)?,
        })
    }

    /// The most pairs one sort may hold.
    pub fn capacity(&self) -> u32 {
        self.capacity
    }

    /// The keys after a sort that returned `true`.
    pub fn scratch_keys(&self) -> &GpuBuffer {
        &self.keys
    }

    /// The values after a sort that returned `true`.
    pub fn scratch_values(&self) -> &GpuBuffer {
        &self.values
    }

    /// Records a stable sort of the first `count` pairs of `keys`/`values` by the low
    /// `key_bits` bits of the keys. Returns whether the sorted pairs are in the scratch
    /// buffers (`true`) or back in `keys`/`values` (`false`).
    pub fn record(
        &mut self,
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        keys: &wgpu::Buffer,
        values: &wgpu::Buffer,
        count: u32,
        key_bits: u32,
    ) -> Result<bool, BackendError> {
        if count > self.capacity {
            return Err(BackendError::Gpu {
                message: format!("sort of {count} pairs in a workspace for {}", self.capacity),
            });
        }
        let passes = key_bits.min(32).div_ceil(DIGIT_BITS);
        if count <= 1 || passes == 0 {
            return Ok(false);
        }
        let blocks = count.div_ceil(BLOCK);
        if self.written_count != count {
            for (pass, params) in (0..).zip(&self.params) {
                context.write(
                    params,
                    0,
                    &[SortParams {
                        count,
                        shift: pass * DIGIT_BITS,
                        blocks,
                        pad: 0,
                    }],
                )?;
            }
            self.written_count = count;
        }
        let count_kernel = context.static_kernel("sort_count", SORT_WGSL, "sort_count")?;
        let scatter_kernel = context.static_kernel("sort_scatter", SORT_WGSL, "sort_scatter")?;
        for pass in 0..passes {
            let (keys_in, values_in, keys_out, values_out) = if pass % 2 == 0 {
                (keys, values, &self.keys.buffer, &self.values.buffer)
            } else {
                (&self.keys.buffer, &self.values.buffer, keys, values)
            };
            let params = &self.params[pass as usize];
            context.dispatch(
                encoder,
                &count_kernel,
                &[(0, params), (1, keys_in), (3, &self.counts.buffer)],
                blocks,
            );
            self.scan
                .record(context, encoder, &self.counts.buffer, blocks * DIGITS)?;
            context.dispatch(
                encoder,
                &scatter_kernel,
                &[
                    (0, params),
                    (1, keys_in),
                    (2, values_in),
                    (3, &self.counts.buffer),
                    (4, keys_out),
                    (5, values_out),
                ],
                blocks,
            );
        }
        Ok(passes % 2 == 1)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::test_support::gpu_test_context;

    /// Records an in-place exclusive prefix sum of the first `count` u32 of `data`. Returns a
    /// buffer whose first element is the total of all `count` values.
    fn exclusive_scan(
        context: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        data: &wgpu::Buffer,
        count: u32,
    ) -> Result<GpuBuffer, BackendError> {
        let mut workspace = ScanWorkspace::new(context, count)?;
        workspace.record(context, encoder, data, count)?;
        Ok(workspace.levels.swap_remove(workspace.total_level).1)
    }

    /// Records a stable sort of `count` pairs by the low `key_bits` bits of their keys.
    /// Consumes the buffers and returns the sorted `(keys, values)` (possibly the same buffers).
    fn radix_sort(
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
        let mut workspace = SortWorkspace::new(context, count)?;
        let in_scratch = workspace.record(
            context,
            encoder,
            &keys.buffer,
            &values.buffer,
            count,
            key_bits,
        )?;
        let (mut keys, mut values) = if in_scratch {
            (workspace.keys, workspace.values)
        } else {
            (keys, values)
        };
        keys.len = count as usize;
        values.len = count as usize;
        Ok((keys, values))
    }

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

    #[test]
    fn reused_workspaces_match_the_cpu_as_counts_change_and_upload_nothing_when_steady() {
        // A context of its own: tests running in parallel on the shared one add their traffic.
        let Some(context) = crate::backend::test_support::gpu_test_context_alone() else {
            return;
        };
        let mut scan = ScanWorkspace::new(&context, 70_000).unwrap();
        let mut sort = SortWorkspace::new(&context, 5_000).unwrap();
        // Up, down, one, none, and the same count twice (the steady state).
        for (round, count) in [
            (0, 70_000_usize),
            (1, 300),
            (2, 1),
            (3, 0),
            (4, 4_000),
            (5, 4_000),
        ] {
            let values: Vec<u32> = pseudo_random(30 + round, count)
                .iter()
                .map(|x| x % 100)
                .collect();
            let data = context
                .upload("scan input", &[values.as_slice(), &[7; 5]].concat())
                .unwrap();
            let before = context.transfers();
            let mut encoder = context.encoder();
            scan.record(&context, &mut encoder, &data.buffer, count as u32)
                .unwrap();
            let traffic = context.transfers().since(&before);
            if round == 5 {
                assert_eq!(traffic.bytes_up, 0, "steady scan uploads");
            }
            let mut pending = context
                .download_many::<u32>(
                    &mut encoder,
                    &[(&data.buffer, count + 5), (&scan.total().buffer, 1)],
                )
                .unwrap();
            context.finish_downloads(encoder, &mut pending).unwrap();
            let mut running = 0;
            let expected: Vec<u32> = values
                .iter()
                .map(|v| {
                    running += v;
                    running - v
                })
                .chain([7; 5])
                .collect();
            assert_eq!(pending[0].values, expected, "scan of {count}");
            assert_eq!(pending[1].values[0], running, "total of {count}");

            let count = count.min(5_000);
            let keys: Vec<u32> = pseudo_random(50 + round, count)
                .iter()
                .map(|x| x % 999)
                .collect();
            let indices: Vec<u32> = (0..count as u32).collect();
            let keys_buffer = context.upload("keys", &keys).unwrap();
            let values_buffer = context.upload("values", &indices).unwrap();
            let before = context.transfers();
            let mut encoder = context.encoder();
            let in_scratch = sort
                .record(
                    &context,
                    &mut encoder,
                    &keys_buffer.buffer,
                    &values_buffer.buffer,
                    count as u32,
                    10,
                )
                .unwrap();
            let traffic = context.transfers().since(&before);
            if round == 5 {
                assert_eq!(traffic.bytes_up, 0, "steady sort uploads");
            }
            let (sorted_keys, sorted_values) = if in_scratch {
                (&sort.scratch_keys().buffer, &sort.scratch_values().buffer)
            } else {
                (&keys_buffer.buffer, &values_buffer.buffer)
            };
            let mut pending = context
                .download_many::<u32>(
                    &mut encoder,
                    &[(sorted_keys, count), (sorted_values, count)],
                )
                .unwrap();
            context.finish_downloads(encoder, &mut pending).unwrap();
            let mut expected: Vec<(u32, u32)> = keys.iter().copied().zip(indices).collect();
            expected.sort_by_key(|pair| pair.0);
            assert_eq!(
                pending[0].values,
                expected.iter().map(|p| p.0).collect::<Vec<_>>(),
                "sorted keys of {count}"
            );
            assert_eq!(
                pending[1].values,
                expected.iter().map(|p| p.1).collect::<Vec<_>>(),
                "sorted values of {count}"
            );
        }
    }
}
