//! Device time between points of recorded work, by timestamp queries where the adapter has
//! them ([`GpuContext::has_timestamps`]): the phases of a training iteration recorded into one
//! command encoder are timed on the device, where host clocks see only the submission.
//!
//! A [`PhaseTimer`] holds a ring of slots (one per recorded iteration), each with `marks`
//! timestamps; [`PhaseTimer::mark`] writes one into the encoder, [`PhaseTimer::finish_slot`]
//! resolves the slot's timestamps into a buffer on the device, and [`PhaseTimer::read`] reads
//! every finished slot back at once (one read-back) as seconds between consecutive marks.

use super::{BackendError, GpuContext};

/// Timestamps between phases of recorded work, in a ring of slots.
pub struct PhaseTimer {
    queries: wgpu::QuerySet,
    resolved: wgpu::Buffer,
    marks: u32,
    slots: u32,
    /// Bytes between two slots in `resolved` (resolve offsets are 256-byte aligned).
    stride: u64,
    /// Nanoseconds per timestamp tick.
    period_ns: f64,
    /// Slots finished since the last read, in order.
    finished: Vec<u32>,
}

impl PhaseTimer {
    /// A timer of `slots` slots of `marks` timestamps each (`marks - 1` phases), or `None`
    /// when the context has no timestamps inside encoders.
    pub fn new(
        context: &GpuContext,
        marks: usize,
        slots: usize,
    ) -> Result<Option<Self>, BackendError> {
        if !context.has_timestamps() {
            return Ok(None);
        }
        let too_many = |what: &str, value: usize| BackendError::BufferTooLarge {
            what: format!("timestamp {what}"),
            bytes: value as u64,
            limit: u64::from(wgpu::QUERY_SET_MAX_QUERIES),
        };
        let count = marks
            .checked_mul(slots)
            .filter(|&count| count >= 2 && count <= wgpu::QUERY_SET_MAX_QUERIES as usize)
            .ok_or_else(|| too_many("queries", marks.saturating_mul(slots)))?;
        let stride = (marks as u64 * 8).next_multiple_of(wgpu::QUERY_RESOLVE_BUFFER_ALIGNMENT);
        let queries = context
            .device()
            .create_query_set(&wgpu::QuerySetDescriptor {
                label: Some("phase timestamps"),
                ty: wgpu::QueryType::Timestamp,
                count: count as u32,
            });
        let resolved = context.device().create_buffer(&wgpu::BufferDescriptor {
            label: Some("phase timestamps resolved"),
            size: stride * slots as u64,
            usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        Ok(Some(Self {
            queries,
            resolved,
            marks: marks as u32,
            slots: slots as u32,
            stride,
            period_ns: f64::from(context.queue().get_timestamp_period()),
            finished: Vec::new(),
        }))
    }

    /// Slots in the ring: the most slots finished between two reads.
    pub fn slots(&self) -> usize {
        self.slots as usize
    }

    /// Records timestamp `mark` of slot `slot` (both taken modulo their counts' range:
    /// `mark < marks`, `slot` wraps around the ring).
    pub fn mark(&self, encoder: &mut wgpu::CommandEncoder, slot: usize, mark: usize) {
        debug_assert!(mark < self.marks as usize);
        let slot = slot as u32 % self.slots;
        encoder.write_timestamp(&self.queries, slot * self.marks + mark as u32);
    }

    /// Records the resolve of slot `slot`'s timestamps (after its last mark). Finishing more
    /// slots than the ring holds before a read drops the oldest.
    pub fn finish_slot(&mut self, encoder: &mut wgpu::CommandEncoder, slot: usize) {
        let slot = slot as u32 % self.slots;
        let first = slot * self.marks;
        encoder.resolve_query_set(
            &self.queries,
            first..first + self.marks,
            &self.resolved,
            u64::from(slot) * self.stride,
        );
        self.finished.retain(|&s| s != slot);
        self.finished.push(slot);
    }

    /// Reads every slot finished since the last read (one read-back; none when there are
    /// none): per slot, in the order finished, the seconds between consecutive marks
    /// (`marks - 1` values; a counter that went backwards reads as zero).
    pub fn read(&mut self, context: &GpuContext) -> Result<Vec<Vec<f64>>, BackendError> {
        if self.finished.is_empty() {
            return Ok(Vec::new());
        }
        let words = (self.stride / 8) as usize * self.slots as usize;
        let ticks: Vec<u64> = context.download(context.encoder(), &self.resolved, words)?;
        let per_slot = (self.stride / 8) as usize;
        let seconds = self
            .finished
            .drain(..)
            .map(|slot| {
                let at = slot as usize * per_slot;
                ticks[at..at + self.marks as usize]
                    .windows(2)
                    .map(|pair| pair[1].saturating_sub(pair[0]) as f64 * self.period_ns * 1e-9)
                    .collect()
            })
            .collect();
        Ok(seconds)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Work recorded between two marks takes device time; an empty phase takes (almost)
    /// none; several slots come back in the order they were finished.
    #[test]
    fn phases_of_recorded_work_are_timed_on_the_device() {
        let Some(context) = crate::backend::test_support::gpu_test_context() else {
            return;
        };
        let Some(mut timer) = PhaseTimer::new(&context, 3, 4).unwrap() else {
            eprintln!("skipped: the adapter has no timestamps inside encoders");
            return;
        };
        let big = context.zeros("timed copy source", 1 << 22, 4).unwrap();
        let copy = context.zeros("timed copy target", 1 << 22, 4).unwrap();
        for slot in [2, 3] {
            let mut encoder = context.encoder();
            timer.mark(&mut encoder, slot, 0);
            for _ in 0..8 {
                encoder.copy_buffer_to_buffer(&big.buffer, 0, &copy.buffer, 0, 4 << 22);
            }
            timer.mark(&mut encoder, slot, 1);
            timer.mark(&mut encoder, slot, 2);
            timer.finish_slot(&mut encoder, slot);
            context.queue().submit([encoder.finish()]);
        }
        let seconds = timer.read(&context).unwrap();
        assert_eq!(seconds.len(), 2);
        for phases in &seconds {
            assert_eq!(phases.len(), 2);
            assert!(phases[0] > 0.0, "{phases:?}");
            assert!(phases[1] <= phases[0], "{phases:?}");
        }
        assert!(timer.read(&context).unwrap().is_empty());
    }
}
