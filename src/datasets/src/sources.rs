//! The files a dataset's reader reads, for the ingest key.

use std::path::PathBuf;

use crate::{DatasetConfig, dna_rendering, i3d_human};

/// The files and folders (every file under a folder counts) that the reader of a file-based
/// dataset reads, for the ingest key: ZJU-MoCap's sequence folder (`annots.npy`, images,
/// masks, fits), I3D-Human's sequence folders (`<ID>-train`, `-novelview`, `-novelpose`:
/// pickles, images, masks) and DNA-Rendering's main and annotation files. The body model is
/// listed by the stage. Optional parts that do not exist are left out (the reader skips them).
pub fn source_files(dataset: &DatasetConfig) -> Vec<PathBuf> {
    match dataset {
        DatasetConfig::Synthetic(_) => vec![],
        DatasetConfig::ZjuMocap(c) => vec![c.root.clone()],
        DatasetConfig::I3dHuman(c) => i3d_human::sequence_folders(&c.root, &c.sequence)
            .into_iter()
            .map(|(_, folder)| folder)
            .collect(),
        DatasetConfig::DnaRendering(c) => {
            let annotations = match &c.annotations_file {
                Some(file) => Some(file.clone()),
                // The reader takes the first candidate that exists.
                None => dna_rendering::annotation_candidates(&c.main_file)
                    .into_iter()
                    .find(|candidate| candidate.is_file()),
            };
            std::iter::once(c.main_file.clone())
                .chain(annotations)
                .collect()
        }
    }
}
