//! The device-side record of every iteration's logged scalars, read back in one round trip
//! every few iterations instead of every iteration.
//!
//! Each resident piece keeps its scalars (losses, PSNR, its status flags) in a small device
//! buffer it owns; after the piece has run, the step copies them into this iteration's slot
//! of the ring (`copy_buffer_to_buffer`: device to device, nothing crosses the bus). The
//! host reads the filled slots when it logs, checkpoints, densifies or finishes.

use seqavatar_compute::backend::{BackendError, GpuBuffer, GpuContext};

/// The scalars of one iteration, in slot order.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LogField {
    L1 = 0,
    MaskMse = 1,
    Dssim = 2,
    Lpips = 3,
    Aiap = 4,
    Psnr = 5,
    /// The image losses' weighted total (AIAP not included).
    ImageTotal = 6,
}

/// Values per slot (one spare, keeping a slot 32 bytes).
pub const LOG_FIELDS: usize = 8;

/// A ring of `capacity` iteration slots of [`LOG_FIELDS`] f32 values on the device.
pub struct LogRing {
    slots: GpuBuffer,
    capacity: usize,
}

impl LogRing {
    /// A zeroed ring of `capacity` slots (at least one).
    pub fn new(context: &GpuContext, capacity: usize) -> Result<Self, BackendError> {
        let capacity = capacity.max(1);
        Ok(Self {
            slots: context.zeros("logged scalars", capacity * LOG_FIELDS, 4)?,
            capacity,
        })
    }

    /// Slots in the ring: the most iterations between two reads.
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Records a copy of the f32 at `index` of `source` into `field` of slot `slot`
    /// (modulo the capacity).
    pub fn record(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        slot: usize,
        field: LogField,
        source: &wgpu::Buffer,
        index: usize,
    ) {
        let target = ((slot % self.capacity) * LOG_FIELDS + field as usize) * 4;
        encoder.copy_buffer_to_buffer(
            source,
            (index * 4) as u64,
            &self.slots.buffer,
            target as u64,
            4,
        );
    }

    /// Records zeros into every field of slot `slot` (an iteration whose pieces do not write
    /// every field starts from zeros, not from the iteration `capacity` slots before).
    pub fn clear_slot(&self, encoder: &mut wgpu::CommandEncoder, slot: usize) {
        let start = ((slot % self.capacity) * LOG_FIELDS * 4) as u64;
        encoder.clear_buffer(&self.slots.buffer, start, Some((LOG_FIELDS * 4) as u64));
    }

    /// Reads slots `first .. first + count` (modulo the capacity; `count` at most the
    /// capacity) in one round trip, after the work recorded so far has run.
    pub fn read(
        &self,
        context: &GpuContext,
        first: usize,
        count: usize,
    ) -> Result<Vec<[f32; LOG_FIELDS]>, BackendError> {
        if count == 0 {
            return Ok(Vec::new());
        }
        if count > self.capacity {
            return Err(BackendError::Gpu {
                message: format!(
                    "{count} iterations since the last read, the log ring holds {}",
                    self.capacity
                ),
            });
        }
        let all = context.download::<f32>(context.encoder(), &self.slots.buffer, self.slots.len)?;
        Ok((first..first + count)
            .map(|slot| {
                let at = (slot % self.capacity) * LOG_FIELDS;
                let mut values = [0.0; LOG_FIELDS];
                values.copy_from_slice(&all[at..at + LOG_FIELDS]);
                values
            })
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_compute::backend::test_support::gpu_test_context_alone;

    #[test]
    fn recorded_scalars_come_back_in_their_slots_and_wrap() {
        // A context of its own: the shared one's traffic counters see the other tests' uploads.
        let Some(context) = gpu_test_context_alone() else {
            return;
        };
        let ring = LogRing::new(&context, 3).unwrap();
        let source = context
            .upload("scalars", &[10.0_f32, 20.0, 30.0, 40.0])
            .unwrap();
        let mut encoder = context.encoder();
        for slot in 0..5 {
            ring.clear_slot(&mut encoder, slot);
            ring.record(&mut encoder, slot, LogField::Psnr, &source.buffer, slot % 4);
            if slot == 0 || slot == 4 {
                ring.record(&mut encoder, slot, LogField::L1, &source.buffer, 0);
            }
        }
        context.submit_and_wait(encoder).unwrap();
        let before = context.transfers();
        let read = ring.read(&context, 2, 3).unwrap();
        let traffic = context.transfers().since(&before);
        assert_eq!(traffic.readbacks, 1);
        assert_eq!(traffic.bytes_up, 0);
        let psnr: Vec<f32> = read.iter().map(|s| s[LogField::Psnr as usize]).collect();
        assert_eq!(psnr, vec![30.0, 40.0, 10.0]);
        assert_eq!(read[2][LogField::L1 as usize], 10.0);
        // Slot 3 shares slot 0's place and was cleared first: its L1 is zero, not slot 0's.
        assert_eq!(read[1][LogField::L1 as usize], 0.0);
        assert!(ring.read(&context, 0, 4).is_err());
    }
}
