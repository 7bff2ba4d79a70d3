//! The test split of an ingest entry (stages/ingest/src/lib.rs, "Output schema"): its cameras,
//! the test (view, frame) pairs, and each pair's ground-truth image and foreground mask cropped
//! to the view's image size.

use seqavatar_core::camera::Camera;
use seqavatar_engine::EntryReader;
use seqavatar_schema::ingest::{GarmentRegion, ImageArrays, read_cameras, read_garment_region};

use crate::metrics::Mask;
use seqavatar_compute::image::ImageF32;

/// One test image: its position on the ingest `image` axis and its (view, frame).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TestImage {
    /// Index on the ingest entry's `image` axis.
    pub index: usize,
    /// Index on the `view` axis.
    pub view: usize,
    /// Index on the `frame` axis.
    pub frame: usize,
}

/// The cameras and test images of one ingest entry.
#[derive(Clone, Debug)]
pub struct TestSet {
    /// Every ingested camera, in `view` order.
    pub cameras: Vec<Camera>,
    /// Test images, in ingest order (by view, then frame).
    pub images: Vec<TestImage>,
    /// Every image of the entry (either split), and the stored size of `images`.
    pub arrays: ImageArrays,
    /// Where the entry's `garment_masks` came from; `None` when it has none.
    pub garment_region: Option<GarmentRegion>,
}

impl TestSet {
    /// Reads the cameras and the test split of an ingest entry.
    pub fn read(entry: &EntryReader) -> anyhow::Result<Self> {
        let cameras = read_cameras(entry)?;
        let arrays = ImageArrays::read(entry)?;
        let images = (0..arrays.len())
            .filter(|&index| arrays.split[index] == 1)
            .map(|index| TestImage {
                index,
                view: arrays.view[index] as usize,
                frame: arrays.frame[index] as usize,
            })
            .collect();
        Ok(Self {
            cameras,
            images,
            arrays,
            garment_region: read_garment_region(entry)?,
        })
    }

    /// The ground-truth image and mask of `image`, cropped to its view's size.
    pub fn load(&self, entry: &EntryReader, image: &TestImage) -> anyhow::Result<(ImageF32, Mask)> {
        let rgb = self.arrays.image(entry, image.index)?;
        let mask = self.arrays.mask(entry, image.index)?;
        let (width, height) = (rgb.width() as usize, rgb.height() as usize);
        let truth = ImageF32::from_rgb8("ingest image", width, height, rgb.as_raw())
            .map_err(|error| anyhow::anyhow!("image {}: {error}", image.index))?;
        let mask = Mask::new("ingest mask", width, height, mask.into_raw())
            .map_err(|error| anyhow::anyhow!("image {}: {error}", image.index))?;
        Ok((truth, mask))
    }

    /// The garment mask of `image` (ingest `garment_masks`), cropped to its view's size;
    /// `None` when the entry has no garment region.
    pub fn load_garment(
        &self,
        entry: &EntryReader,
        image: &TestImage,
    ) -> anyhow::Result<Option<Mask>> {
        if self.garment_region.is_none() {
            return Ok(None);
        }
        let garment = self.arrays.garment_mask(entry, image.index)?;
        let (width, height) = (garment.width() as usize, garment.height() as usize);
        let garment = Mask::new("ingest garment mask", width, height, garment.into_raw())
            .map_err(|error| anyhow::anyhow!("image {}: {error}", image.index))?;
        Ok(Some(garment))
    }
}
