//! Device selection and the wgpu context (filled in by the backend work).
