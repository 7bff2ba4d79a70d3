//! Safe readers for the Python-side file formats the datasets use: pickles (with numpy arrays,
//! dtypes, scalars and OrderedDicts), `.npy` and `.npz`. They execute nothing, accept only
//! known globals and never allocate more than the input can justify.

pub mod dtype;
pub mod npy;
pub mod npz;
pub mod pickle;
pub mod value;

pub use value::{ArrayData, NpArray, Value};
