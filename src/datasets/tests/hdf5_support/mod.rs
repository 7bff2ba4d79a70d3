//! `.smc` facts read with `hdf5-reader` directly, as a check independent of
//! [`seqavatar_datasets::smc::SmcFile`]. Not in `support`, which the formats tests include
//! without that crate.

use std::path::Path;

/// Shape and numpy's `dtype.str` (`"<f8"`, `">i4"`, `"|u1"`) of the numeric dataset `name`
/// of the HDF5 file at `path`, read with `hdf5-reader` itself.
pub fn dataset_info(path: &Path, name: &str) -> (Vec<u64>, String) {
    use hdf5_reader::{ByteOrder, Datatype};
    let file = hdf5_reader::Hdf5File::open(path).unwrap();
    let dataset = file
        .dataset(name)
        .unwrap_or_else(|e| panic!("{} `{name}`: {e}", path.display()));
    let (kind, size, order) = match dataset.dtype() {
        Datatype::FixedPoint {
            size,
            signed,
            byte_order,
        } => (if *signed { 'i' } else { 'u' }, *size, *byte_order),
        Datatype::FloatingPoint { size, byte_order } => ('f', *size, *byte_order),
        _ => panic!("{} `{name}`: not a numeric dataset", path.display()),
    };
    let order = match (size, order) {
        (1, _) => '|',
        (_, ByteOrder::BigEndian) => '>',
        _ => '<',
    };
    (dataset.shape().to_vec(), format!("{order}{kind}{size}"))
}
