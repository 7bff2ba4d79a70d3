//! The test split of an ingest entry (stages/ingest/src/lib.rs, "Output schema"): its cameras,
//! the test (view, frame) pairs, and each pair's ground-truth image and foreground mask cropped
//! to the view's image size.

use seqavatar_core::camera::Camera;
use seqavatar_engine::EntryReader;

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
    /// The dataset's camera id per view.
    pub camera_source_ids: Vec<i64>,
    /// The dataset's frame number per frame.
    pub frame_source_ids: Vec<i64>,
    /// Test images, in ingest order (by view, then frame).
    pub images: Vec<TestImage>,
    /// Height and width of the ingest `images` array (the largest view).
    pub stored_height: usize,
    pub stored_width: usize,
    /// Where the entry's `garment_masks` came from; `None` when it has none.
    pub garment_region: Option<seqavatar_schema::ingest::GarmentRegion>,
}

/// Checks a shape; `None` matches any extent.
pub fn check_shape(
    entry: &EntryReader,
    name: &str,
    shape: &[usize],
    expected: &[Option<usize>],
) -> anyhow::Result<()> {
    let matches = shape.len() == expected.len()
        && shape
            .iter()
            .zip(expected)
            .all(|(&extent, wanted)| wanted.is_none_or(|wanted| wanted == extent));
    anyhow::ensure!(
        matches,
        "entry {} ({}): array \"{name}\" has shape {shape:?}, expected {}",
        entry.stage_name(),
        entry.location(),
        describe_shape(expected)
    );
    Ok(())
}

fn describe_shape(expected: &[Option<usize>]) -> String {
    let parts: Vec<String> = expected
        .iter()
        .map(|extent| extent.map_or_else(|| "_".to_owned(), |value| value.to_string()))
        .collect();
    format!("({})", parts.join(", "))
}

impl TestSet {
    /// Reads the cameras and the test split of an ingest entry.
    pub fn read(entry: &EntryReader) -> anyhow::Result<Self> {
        let cameras = seqavatar_schema::ingest::read_cameras(entry)?;
        let views = cameras.len();
        let camera_source_ids = entry.read::<i64>("camera_source_id")?;
        check_shape(
            entry,
            "camera_source_id",
            &camera_source_ids.shape,
            &[Some(views)],
        )?;
        let frame_source_ids = entry.read::<i64>("frame_source_id")?;
        let frames = frame_source_ids.data.len();
        let image_view = entry.read::<u32>("image_view")?;
        let count = image_view.data.len();
        let image_frame = entry.read::<u32>("image_frame")?;
        check_shape(entry, "image_frame", &image_frame.shape, &[Some(count)])?;
        let image_split = entry.read::<u8>("image_split")?;
        check_shape(entry, "image_split", &image_split.shape, &[Some(count)])?;
        let stored = entry.shape("images")?;
        anyhow::ensure!(
            stored.len() == 4 && stored[0] as usize == count && stored[3] == 3,
            "entry {} ({}): array \"images\" has shape {stored:?}, expected ({count}, height, width, 3)",
            entry.stage_name(),
            entry.location()
        );
        let (stored_height, stored_width) = (stored[1] as usize, stored[2] as usize);
        let mut images = Vec::new();
        for index in 0..count {
            if image_split.data[index] != 1 {
                continue;
            }
            let (view, frame) = (
                image_view.data[index] as usize,
                image_frame.data[index] as usize,
            );
            anyhow::ensure!(
                view < views && frame < frames,
                "entry {} ({}): image {index} names view {view} and frame {frame}, but the entry has {views} views and {frames} frames",
                entry.stage_name(),
                entry.location()
            );
            let camera = &cameras[view];
            anyhow::ensure!(
                camera.height as usize <= stored_height && camera.width as usize <= stored_width,
                "entry {} ({}): view {view} is {} x {}, larger than the images array ({stored_width} x {stored_height})",
                entry.stage_name(),
                entry.location(),
                camera.width,
                camera.height
            );
            images.push(TestImage { index, view, frame });
        }
        Ok(Self {
            cameras,
            camera_source_ids: camera_source_ids.data,
            frame_source_ids: frame_source_ids.data,
            images,
            stored_height,
            stored_width,
            garment_region: seqavatar_schema::ingest::read_garment_region(entry)?,
        })
    }

    /// The ground-truth image and mask of `image`, cropped to its view's size.
    pub fn load(&self, entry: &EntryReader, image: &TestImage) -> anyhow::Result<(ImageF32, Mask)> {
        let camera = &self.cameras[image.view];
        let (width, height) = (camera.width as usize, camera.height as usize);
        let start = [image.index as u64, 0, 0, 0];
        let rgb =
            entry.read_region::<u8>("images", &start, &[1, height as u64, width as u64, 3])?;
        let mask =
            entry.read_region::<u8>("masks", &start[..3], &[1, height as u64, width as u64])?;
        let what = "ingest image";
        let truth = ImageF32::from_rgb8(what, width, height, &rgb.data)
            .map_err(|error| anyhow::anyhow!("image {}: {error}", image.index))?;
        let mask = Mask::new("ingest mask", width, height, mask.data)
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
        let camera = &self.cameras[image.view];
        let (width, height) = (camera.width as usize, camera.height as usize);
        let garment = entry.read_region::<u8>(
            seqavatar_schema::ingest::GARMENT_MASKS,
            &[image.index as u64, 0, 0],
            &[1, height as u64, width as u64],
        )?;
        let garment = Mask::new("ingest garment mask", width, height, garment.data)
            .map_err(|error| anyhow::anyhow!("image {}: {error}", image.index))?;
        Ok(Some(garment))
    }
}
