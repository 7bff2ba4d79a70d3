//! The hierarchical motion context of a body sequence, on plain arrays: the template posed at
//! every frame, per-joint rotations, skeleton motion and vertex velocity per (frame, scale),
//! and the canonical template with its KNN graph. The motion stage stores them
//! ([`seqavatar_schema::motion`]); `pipeline render` computes them for a new pose sequence
//! ([`compute::motion_track_for`]).

pub mod compute;
pub mod context;
pub mod pose;
