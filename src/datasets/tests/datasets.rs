//! The dataset readers on tiny datasets written in each real layout by
//! `tests/fixtures/write_datasets.py` (numpy.save of pickled dicts, pickle with OrderedDict,
//! h5py with JPEG bytes and string attributes). Expectations come from numpy: camera
//! matrices, the pixel a known 3D point projects to (full resolution and rescaled), SMPL
//! world vertices from an independent numpy LBS, body parameters, decoded images and masks.

mod hdf5_support;
mod support;

use std::path::Path;

use seqavatar_core::glam::DVec3;
use seqavatar_datasets::body_model::{ComponentLimits, load_body_model_npz};
use seqavatar_datasets::dna_rendering::DnaRendering;
use seqavatar_datasets::i3d_human::I3dHuman;
use seqavatar_datasets::smc::SmcFile;
use seqavatar_datasets::zju_mocap::ZjuMocap;
use seqavatar_datasets::{BodyModelKind, DatasetReader, SourceCamera};
use seqavatar_formats::{ArrayData, Value, npy};
use seqavatar_schema::ingest::GarmentRegion;
use support::{assert_close, dataset_fixture, f64s, read_json};

fn expected_array(path: &Path) -> (Vec<usize>, Vec<u8>) {
    match npy::read(&std::fs::read(path).unwrap()).unwrap() {
        Value::Array(a) => match a.data {
            ArrayData::U8(v) => (a.shape, v),
            other => panic!("{}: not uint8: {other:?}", path.display()),
        },
        other => panic!("{}: not an array: {other}", path.display()),
    }
}

/// Checks a camera against the numpy expectation, including the pixel of a known point at
/// full resolution and after rescaling by `scale`.
fn check_camera(
    source: &SourceCamera,
    expected: &serde_json::Value,
    point: DVec3,
    scale: Option<(f64, &str)>,
) {
    let camera = &source.camera;
    let k: Vec<f64> = camera.k_matrix().iter().flatten().copied().collect();
    assert_close(&k, &f64s(&expected["K"]), 1e-12, "K");
    let r: Vec<f64> = camera.rotation.transpose().to_cols_array().to_vec();
    assert_close(&r, &f64s(&expected["R"]), 1e-12, "R (row-major)");
    assert_close(
        &camera.translation.to_array(),
        &f64s(&expected["t"]),
        1e-12,
        "t",
    );
    let pixel = camera.project(point).expect("in front of the camera");
    assert_close(
        &pixel.to_array(),
        &f64s(&expected["point_pixel"]),
        1e-9,
        "pixel of the known point",
    );
    if let Some((factor, key)) = scale {
        let rescaled = camera.rescaled(factor);
        let pixel = rescaled.project(point).unwrap();
        assert_close(
            &pixel.to_array(),
            &f64s(&expected[key]),
            1e-9,
            "rescaled pixel",
        );
    }
}

fn point_of(expected: &serde_json::Value) -> DVec3 {
    let p = f64s(&expected["point"]);
    DVec3::new(p[0], p[1], p[2])
}

fn assert_error_mentions(result: anyhow::Result<impl Sized>, needles: &[&str]) {
    let message = match result {
        Ok(_) => panic!("expected an error mentioning {needles:?}"),
        Err(e) => format!("{e:#}"),
    };
    for needle in needles {
        assert!(
            message.contains(needle),
            "error {message:?} does not mention {needle:?}"
        );
    }
}

fn image_close(actual: &[u8], expected: &[u8], what: &str) {
    assert_eq!(actual.len(), expected.len(), "{what}: size");
    // Two JPEG decoders differ slightly (IDCT rounding, chroma upsampling).
    let worst = actual
        .iter()
        .zip(expected)
        .map(|(a, b)| a.abs_diff(*b))
        .max()
        .unwrap_or(0);
    let mean = actual
        .iter()
        .zip(expected)
        .map(|(a, b)| f64::from(a.abs_diff(*b)))
        .sum::<f64>()
        / actual.len().max(1) as f64;
    assert!(
        worst <= 8 && mean < 1.0,
        "{what}: largest difference {worst}, mean {mean}"
    );
}

#[test]
fn zju_mocap_reads_cameras_images_masks_and_fits() {
    let dir = dataset_fixture("zju");
    let root = dir.path().join("CoreView_377");
    let smpl = dir.path().join("smpl.npz");
    let expected = read_json(&dir.path().join("expected.json"));
    let reader = ZjuMocap::open(&root, Some(&smpl)).unwrap();
    let point = point_of(&expected);
    assert_eq!(reader.cameras().len(), 3);
    for (c, camera) in reader.cameras().iter().enumerate() {
        let e = &expected["cameras"][c];
        assert_eq!(camera.id, e["id"].as_i64().unwrap());
        assert_eq!((camera.camera.width, camera.camera.height), (40, 32));
        assert_close(
            &camera.camera.distortion,
            &f64s(&e["distortion"]),
            0.0,
            "distortion",
        );
        check_camera(camera, e, point, Some((0.5, "point_pixel_half")));
    }
    assert_eq!(reader.num_frames(), 4);
    assert_eq!(reader.frame_id(3), 3);
    for view in 0..3 {
        for frame in 0..4 {
            let image = reader.read_image(view, frame).unwrap();
            let (shape, rgb) =
                expected_array(&dir.path().join(format!("expected_rgb_{view}_{frame}.npy")));
            assert_eq!(shape, vec![32, 40, 3]);
            image_close(image.rgb.as_raw(), &rgb, "rgb");
            let (_, mask) =
                expected_array(&dir.path().join(format!("expected_mask_{view}_{frame}.npy")));
            assert_eq!(image.mask.as_raw(), &mask, "mask view {view} frame {frame}");
        }
    }
    // Fits, and the Rh/Th convention: our forward pass reproduces numpy's world vertices.
    let (model, kind) = reader.body_model().unwrap();
    assert_eq!(kind, BodyModelKind::Smpl);
    for frame in 0..4 {
        let params = reader.body_params(frame).unwrap();
        let e = &expected["params"][frame];
        let pose: Vec<f64> = params.pose.iter().flat_map(|v| v.to_array()).collect();
        assert_close(&pose, &f64s(&e["poses"]), 0.0, "poses");
        assert_close(
            &params.world_rotation.to_array(),
            &f64s(&e["Rh"]),
            0.0,
            "Rh",
        );
        assert_close(
            &params.world_translation.to_array(),
            &f64s(&e["Th"]),
            0.0,
            "Th",
        );
        assert_close(&params.betas, &f64s(&e["shapes"]), 0.0, "shapes");
        let posed = model.forward(&params).unwrap();
        let vertices =
            npy::read(&std::fs::read(root.join(format!("new_vertices/{frame}.npy"))).unwrap())
                .unwrap();
        let (shape, want) = vertices.to_f64_array().unwrap();
        assert_eq!(shape, vec![8, 3]);
        let got: Vec<f64> = posed.vertices.iter().flat_map(|v| v.to_array()).collect();
        assert_close(&got, &want, 1e-9, "world vertices");
    }
    let split = reader.default_split();
    assert_eq!(split.train_views, vec![0]);
    assert_eq!(split.test_views, vec![1, 2]);
    assert_eq!(split.train_frames.end, Some(4));
    assert_eq!(split.test_frames.step, 30);
}

/// `mask_cihp/` holds CIHP part labels: the foreground is every non-zero label, the garment
/// region the clothing labels (5 upper clothes, 6 dress, 7 coat, 9 pants, 11 scarf, 12 skirt;
/// not 10, torso skin, nor 13 face or 14 left arm). The committed fixture's masks are all
/// label 7 (coat), so the region is the whole person there; a label image written here as
/// the fixture script writes its masks (an 8-bit grey PNG of labels) checks each label. With
/// `mask/` (0/1) there is no garment region; a file holding a value that is no CIHP label
/// loads with an empty region.
#[test]
fn zju_mocap_garment_region_is_the_cihp_clothing_labels() {
    let dir = dataset_fixture("zju");
    let root = dir.path().join("CoreView_377");
    let reader = ZjuMocap::open(&root, None).unwrap();
    assert_eq!(reader.garment_region(), Some(GarmentRegion::CihpClothing));
    let (image, garment) = reader.read_image_with_garment(1, 2).unwrap();
    let garment = garment.expect("a garment mask with mask_cihp");
    assert_eq!(
        garment.as_raw(),
        image.mask.as_raw(),
        "label 7 (coat) is clothing"
    );
    assert!(garment.contains(&255));

    // Every label in its own column band of the 40 x 32 image.
    let labels: Vec<u8> = (0..=19).collect();
    let label_at = |x: u32| labels[(x as usize) / 2];
    let parts = image::GrayImage::from_fn(40, 32, |x, _| image::Luma([label_at(x)]));
    let path = root.join("mask_cihp/Camera_B2/000002.png");
    parts.save(&path).unwrap();
    let (image, garment) = reader.read_image_with_garment(1, 2).unwrap();
    let garment = garment.unwrap();
    for x in 0..40 {
        let label = label_at(x);
        let clothing = [5, 6, 7, 9, 11, 12].contains(&label);
        assert_eq!(
            garment.get_pixel(x, 5).0[0],
            if clothing { 255 } else { 0 },
            "label {label}"
        );
        assert_eq!(
            image.mask.get_pixel(x, 5).0[0],
            if label != 0 { 255 } else { 0 },
            "label {label}"
        );
    }
    // `read_image` gives the same image and mask.
    assert_eq!(reader.read_image(1, 2).unwrap(), image);

    // A file holding a value that is no CIHP label (here a 0/255 matte with one label-5
    // column) still loads: the person is every non-zero pixel, the garment region is empty.
    let matte = image::GrayImage::from_fn(40, 32, |x, _| {
        image::Luma([match x {
            0..=9 => 0,
            10 => 5,
            _ => 255,
        }])
    });
    matte.save(&path).unwrap();
    let (image, garment) = reader.read_image_with_garment(1, 2).unwrap();
    assert!(
        garment.unwrap().iter().all(|&v| v == 0),
        "no garment region"
    );
    assert_eq!(image.mask.get_pixel(5, 5).0[0], 0);
    assert_eq!(image.mask.get_pixel(10, 5).0[0], 255);
    assert_eq!(image.mask.get_pixel(20, 5).0[0], 255);

    // `mask/` (0/1): no garment region.
    std::fs::rename(root.join("mask_cihp"), root.join("mask")).unwrap();
    let reader = ZjuMocap::open(&root, None).unwrap();
    assert_eq!(reader.garment_region(), None);
    let (image, garment) = reader.read_image_with_garment(0, 1).unwrap();
    assert!(garment.is_none());
    assert!(image.mask.contains(&255));
}

#[test]
fn zju_mocap_bad_input_names_file_and_field() {
    let dir = dataset_fixture("zju");
    let root = dir.path().join("CoreView_377");
    let variants = dir.path().join("variants");
    // A camera missing from one of the calibration lists.
    let good_annots = std::fs::read(root.join("annots.npy")).unwrap();
    std::fs::copy(
        variants.join("annots_missing_camera.npy"),
        root.join("annots.npy"),
    )
    .unwrap();
    assert_error_mentions(
        ZjuMocap::open(&root, None),
        &["annots.npy", "cams.T", "2 cameras"],
    );
    std::fs::write(root.join("annots.npy"), good_annots).unwrap();
    let reader = ZjuMocap::open(&root, None).unwrap();
    // A NaN in the pose, and a pose of the wrong length.
    std::fs::copy(
        variants.join("params_nan.npy"),
        root.join("new_params/1.npy"),
    )
    .unwrap();
    assert_error_mentions(
        reader.body_params(1),
        &["new_params/1.npy", "`poses`", "NaN"],
    );
    std::fs::copy(
        variants.join("params_short.npy"),
        root.join("new_params/2.npy"),
    )
    .unwrap();
    assert_error_mentions(
        reader.body_params(2),
        &["new_params/2.npy", "`poses`", "expected 72 values"],
    );
    // A truncated image, and a mask of the wrong size.
    let image = root.join("Camera_B2/000001.jpg");
    let bytes = std::fs::read(&image).unwrap();
    std::fs::write(&image, &bytes[..bytes.len() / 2]).unwrap();
    assert_error_mentions(reader.read_image(1, 1), &["Camera_B2/000001.jpg"]);
    std::fs::copy(
        variants.join("mask_small.png"),
        root.join("mask_cihp/Camera_B3/000002.png"),
    )
    .unwrap();
    assert_error_mentions(
        reader.read_image(2, 2),
        &["mask_cihp/Camera_B3/000002.png", "38x32", "40x32"],
    );
    // No body model configured.
    assert_error_mentions(reader.body_model(), &["body_model"]);
}

#[test]
fn i3d_human_merges_folders_and_reads_pickled_cameras() {
    let dir = dataset_fixture("i3d");
    let expected = read_json(&dir.path().join("expected.json"));
    let smpl = dir.path().join("smpl.npz");
    let reader = I3dHuman::open(dir.path(), "ID2_1", Some(&smpl)).unwrap();
    let ids: Vec<i64> = reader.cameras().iter().map(|c| c.id).collect();
    assert_eq!(ids, vec![1, 2, 3]);
    let point = point_of(&expected);
    for camera in reader.cameras() {
        let e = &expected["cameras"][camera.id.to_string()];
        assert_eq!((camera.camera.width, camera.camera.height), (24, 20));
        check_camera(camera, e, point, None);
    }
    assert_eq!(reader.num_frames(), 12);
    for frame in 0..12 {
        let params = reader.body_params(frame).unwrap();
        let e = &expected["params"][frame.to_string()];
        let pose: Vec<f64> = params.pose.iter().flat_map(|v| v.to_array()).collect();
        assert_close(
            &pose,
            &f64s(&e["poses"]),
            0.0,
            &format!("poses of frame {frame}"),
        );
        assert_close(
            &params.world_rotation.to_array(),
            &f64s(&e["Rh"]),
            0.0,
            "Rh",
        );
        assert_close(
            &params.world_translation.to_array(),
            &f64s(&e["Th"]),
            0.0,
            "Th",
        );
        assert!(params.betas.is_empty());
    }
    // Train view 3 (index 2) at frame 6, novel view 2 (index 1), novel pose view 1 at frame 9.
    for (view, id, frame) in [(2, 3, 6), (1, 2, 3), (0, 1, 9)] {
        let image = reader.read_image(view, frame).unwrap();
        let (_, rgb) = expected_array(&dir.path().join(format!("expected_rgb_{id}_{frame}.npy")));
        assert_eq!(image.rgb.as_raw(), &rgb, "PNG images decode exactly");
        assert!(image.mask.as_raw().iter().all(|&m| m == 0 || m == 255));
        assert!(image.mask.as_raw().contains(&255));
    }
    assert_error_mentions(reader.read_image(1, 9), &["no image of view 2 at frame 9"]);
    let split = reader.default_split();
    // ID2_1: train views 1, 3, 5, 7, 9 and test 2, 4, 6, 10, of which 1, 3 and 2 exist.
    assert_eq!(split.train_views, vec![0, 2]);
    assert_eq!(split.test_views, vec![1]);
    assert_eq!(split.frame_interval, 3);
    assert_eq!(
        (
            split.train_frames.start,
            split.train_frames.end,
            split.train_frames.step
        ),
        (0, Some(7), 3)
    );
    let (_, kind) = reader.body_model().unwrap();
    assert_eq!(kind, BodyModelKind::Smpl);
}

#[test]
fn dna_rendering_reads_smc_pairs() {
    let dir = dataset_fixture("dna");
    let expected = read_json(&dir.path().join("expected.json"));
    let main = dir.path().join("dna_rendering_part1_main/0007_04.smc");
    let smplx = dir.path().join("smplx.npz");
    let reader = DnaRendering::open(&main, None, Some(&smplx)).unwrap();
    assert_eq!(reader.gender.as_deref(), Some("female"));
    let ids: Vec<i64> = reader.cameras().iter().map(|c| c.id).collect();
    assert_eq!(ids, vec![0, 2, 48]);
    let point = point_of(&expected);
    for camera in reader.cameras() {
        let e = &expected["cameras"][camera.id.to_string()];
        let size = (
            e["width"].as_u64().unwrap() as u32,
            e["height"].as_u64().unwrap() as u32,
        );
        assert_eq!((camera.camera.width, camera.camera.height), size);
        check_camera(camera, e, point, Some((0.25, "point_pixel_quarter")));
    }
    assert_eq!(reader.num_frames(), 3);
    for (view, id) in [(0, 0), (2, 48)] {
        for frame in 0..3 {
            let image = reader.read_image(view, frame).unwrap();
            let (_, rgb) =
                expected_array(&dir.path().join(format!("expected_rgb_{id}_{frame}.npy")));
            image_close(image.rgb.as_raw(), &rgb, "rgb");
            let (_, mask) =
                expected_array(&dir.path().join(format!("expected_mask_{id}_{frame}.npy")));
            assert_eq!(image.mask.as_raw(), &mask, "soft mask, max over channels");
        }
    }
    // SMPL-X: the mean hand pose is added; betas (one row) and expression (two rows) are
    // broadcast to three frames with warnings; camera 01 has no images (warning).
    let pose = f64s(&expected["pose"]);
    let transl = f64s(&expected["transl"]);
    let betas = f64s(&expected["betas"]);
    let expression = f64s(&expected["expression"]);
    for frame in 0..3 {
        let params = reader.body_params(frame).unwrap();
        let got: Vec<f64> = params.pose.iter().flat_map(|v| v.to_array()).collect();
        assert_close(
            &got,
            &pose[frame * 165..(frame + 1) * 165],
            1e-12,
            "pose + hand mean",
        );
        assert_close(
            &params.world_translation.to_array(),
            &transl[frame * 3..frame * 3 + 3],
            0.0,
            "transl",
        );
        assert_eq!(params.world_rotation, DVec3::ZERO);
        assert_close(&params.betas, &betas, 0.0, "betas");
        assert_close(
            &params.expression,
            &expression[frame * 10..frame * 10 + 10],
            0.0,
            "expression",
        );
    }
    // 3D keypoints carried as stored, with the confidence column; the NaN keypoint
    // (frame 1, keypoint 4) has confidence 0; no joint correspondence is documented.
    let keypoints = reader
        .keypoints_3d()
        .unwrap()
        .expect("fixture has Keypoints_3D");
    assert_eq!(keypoints.joints, vec![None; 10]);
    let positions: Vec<f64> = keypoints
        .positions
        .iter()
        .map(|p| if p.is_finite() { *p } else { DVec3::ZERO })
        .flat_map(|p| p.to_array())
        .collect();
    assert_close(
        &positions,
        &f64s(&expected["keypoints3d"]),
        0.0,
        "keypoints",
    );
    assert_close(
        &keypoints.confidence,
        &f64s(&expected["keypoints3d_confidence"]),
        0.0,
        "keypoint confidence",
    );
    assert_eq!(keypoints.confidence[14], 0.0);
    assert_eq!(reader.warnings.len(), 3, "{:?}", reader.warnings);
    assert!(
        reader
            .warnings
            .iter()
            .any(|w| w.contains("SMPLx/betas") && w.contains("1 rows for 3 frames"))
    );
    assert!(
        reader
            .warnings
            .iter()
            .any(|w| w.contains("SMPLx/expression") && w.contains("2 rows"))
    );
    let (model, kind) = reader.body_model().unwrap();
    assert_eq!(kind, BodyModelKind::Smplx);
    assert_eq!(
        (
            model.num_joints(),
            model.num_betas(),
            model.num_expression()
        ),
        (55, 10, 10)
    );
    let split = reader.default_split();
    assert_eq!(split.train_views, vec![0, 1]);
    assert_eq!(split.test_views, vec![2]);
}

#[test]
fn dna_rendering_without_annotations_or_with_a_bad_image_fails_clearly() {
    let dir = dataset_fixture("dna");
    let main = dir.path().join("dna_rendering_part1_main/0007_04.smc");
    let annotations = dir
        .path()
        .join("dna_rendering_part1_annotations/0007_04_annots.smc");
    // Side by side is accepted too.
    let side = dir
        .path()
        .join("dna_rendering_part1_main/0007_04_annots.smc");
    std::fs::rename(&annotations, &side).unwrap();
    assert!(DnaRendering::open(&main, None, None).is_ok());
    std::fs::remove_file(&side).unwrap();
    assert_error_mentions(
        DnaRendering::open(&main, None, None),
        &[
            "0007_04.smc",
            "annotation file is missing",
            "0007_04_annots.smc",
        ],
    );
    // An annotation file that is not HDF5.
    std::fs::write(&annotations, b"not hdf5").unwrap();
    assert_error_mentions(
        DnaRendering::open(&main, None, None),
        &["0007_04_annots.smc", "HDF5"],
    );
}

/// A full-size body model saved with `np.savez_compressed` whose float64 blend shapes are
/// all zeros (66 MB of `posedirs` from a file of a few hundred KB) loads: the readers judge
/// arrays by the size they declare, not by their compression ratio (the old limit, 32 times
/// the file's size plus 32 MiB, refused it).
#[test]
fn a_compressed_body_model_with_zero_blend_shapes_loads() {
    let dir = dataset_fixture("smpl_compressed");
    let expected = read_json(&dir.path().join("expected.json"));
    let path = dir.path().join("model.npz");
    let file_len = std::fs::metadata(&path).unwrap().len() as usize;
    let decoded = expected["decoded_bytes"].as_u64().unwrap() as usize;
    assert!(file_len < 1_000_000, "{file_len}");
    assert!(
        decoded > 32 * file_len + (32 << 20),
        "the fixture must compress better than the old ratio limit: {decoded} from {file_len}"
    );
    let loaded = load_body_model_npz(&path, ComponentLimits::default()).unwrap();
    assert_eq!(loaded.model.num_joints(), 24);
    let vertices = expected["num_vertices"].as_u64().unwrap() as usize;
    assert_eq!(loaded.model.num_vertices(), vertices);
    assert!(loaded.model.arrays().pose_dirs.iter().all(|&x| x == 0.0));
    for (index, key) in [(0, "first_vertex"), (vertices - 1, "last_vertex")] {
        let want = f64s(&expected[key]);
        let got = loaded.model.template_vertex(index);
        for axis in 0..3 {
            assert!(
                (got[axis] - want[axis]).abs() < 1e-12,
                "{key}: {got} vs {want:?}"
            );
        }
    }
}

#[test]
fn body_model_npz_loads_smpl_and_smplx() {
    for kind in ["smpl", "smplx"] {
        let dir = dataset_fixture(kind);
        let expected = read_json(&dir.path().join("expected.json"));
        let loaded =
            load_body_model_npz(&dir.path().join("model.npz"), ComponentLimits::default()).unwrap();
        let joints = if kind == "smpl" { 24 } else { 55 };
        assert_eq!(loaded.model.num_joints(), joints);
        assert_eq!(
            loaded.model.num_betas(),
            10,
            "{kind}: truncated to 10 betas"
        );
        assert_eq!(
            loaded.model.num_expression(),
            if kind == "smpl" { 0 } else { 10 }
        );
        assert_eq!(loaded.hands_mean.is_some(), kind == "smplx");
        let pose = f64s(&expected["pose"]);
        let rh = f64s(&expected["Rh"]);
        let th = f64s(&expected["Th"]);
        let params = seqavatar_core::body::BodyParams {
            pose: pose
                .chunks_exact(3)
                .map(|c| DVec3::new(c[0], c[1], c[2]))
                .collect(),
            betas: f64s(&expected["betas"]),
            expression: f64s(&expected["expression"]),
            world_rotation: DVec3::new(rh[0], rh[1], rh[2]),
            world_translation: DVec3::new(th[0], th[1], th[2]),
        };
        let posed = loaded.model.forward(&params).unwrap();
        let got: Vec<f64> = posed.vertices.iter().flat_map(|v| v.to_array()).collect();
        assert_close(
            &got,
            &f64s(&expected["vertices"]),
            1e-9,
            &format!("{kind} vertices"),
        );
    }
}

/// Every file under `dir` (recursively), as `/`-separated paths relative to `root`.
fn files_under(root: &Path, dir: &Path, out: &mut Vec<String>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let entry = entry.unwrap();
        if entry.file_type().unwrap().is_dir() {
            files_under(root, &entry.path(), out);
        } else {
            let relative = entry.path().strip_prefix(root).unwrap().to_owned();
            let parts: Vec<String> = relative
                .components()
                .map(|c| c.as_os_str().to_string_lossy().into_owned())
                .collect();
            out.push(parts.join("/"));
        }
    }
}

/// The committed fixtures are exactly what `tests/fixtures/regenerate.py` wrote: the same
/// files, each with the recorded size and blake3 digest, every `.npy` with the recorded
/// shape and dtype, every `.smc` with the recorded datasets (shape and dtype, read with our
/// HDF5 reader). Regenerate with `python3 tests/fixtures/regenerate.py`.
#[test]
fn fixture_manifest() {
    let root = support::fixture_data_dir();
    let manifest = read_json(&root.join("MANIFEST.json"));
    let entries = manifest["files"].as_array().expect("files");
    let mut listed: Vec<String> = entries
        .iter()
        .map(|e| e["path"].as_str().unwrap().to_owned())
        .collect();
    let mut present = Vec::new();
    files_under(&root, &root, &mut present);
    present.retain(|p| p != "MANIFEST.json");
    listed.sort();
    present.sort();
    assert_eq!(
        present, listed,
        "tests/fixtures/data differs from MANIFEST.json: run `python3 tests/fixtures/regenerate.py`"
    );
    let mut total = 0;
    for entry in entries {
        let path = entry["path"].as_str().unwrap();
        let bytes = std::fs::read(root.join(path)).unwrap();
        total += bytes.len() as u64;
        assert_eq!(
            bytes.len() as u64,
            entry["bytes"].as_u64().unwrap(),
            "{path}: size"
        );
        assert_eq!(
            blake3::hash(&bytes).to_hex().as_str(),
            entry["blake3"].as_str().unwrap(),
            "{path}: digest (edited by hand? regenerate with `python3 tests/fixtures/regenerate.py`)"
        );
        if path.ends_with(".npy") {
            let header = npy::read_header(&bytes).unwrap_or_else(|e| panic!("{path}: {e}"));
            let shape: Vec<usize> = entry["shape"]
                .as_array()
                .unwrap()
                .iter()
                .map(|d| d.as_u64().unwrap() as usize)
                .collect();
            assert_eq!(header.shape, shape, "{path}: shape");
            assert_eq!(
                header.dtype.descr(),
                entry["dtype"].as_str().unwrap(),
                "{path}: dtype"
            );
        }
        if path.ends_with(".smc") {
            let file = SmcFile::open(&root.join(path)).unwrap();
            let want = entry["datasets"].as_object().unwrap();
            let mut got = Vec::new();
            file.walk(
                |_| Ok(()),
                |dataset| {
                    got.push(dataset.to_owned());
                    Ok(())
                },
            )
            .unwrap();
            got.sort();
            let mut names: Vec<String> = want.keys().cloned().collect();
            names.sort();
            assert_eq!(got, names, "{path}: datasets");
            for (dataset, info) in want {
                let (shape, dtype) = hdf5_support::dataset_info(&root.join(path), dataset);
                let want_shape: Vec<u64> = info[0]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|d| d.as_u64().unwrap())
                    .collect();
                assert_eq!(shape, want_shape, "{path} `{dataset}`: shape");
                assert_eq!(
                    dtype,
                    info[1].as_str().unwrap(),
                    "{path} `{dataset}`: dtype"
                );
            }
        }
    }
    assert_eq!(total, manifest["total_bytes"].as_u64().unwrap());
    // Small enough to commit: under 1 MB in all (the compressed body model, whose 66 MB
    // of zero blend shapes cannot deflate below about 64 KB, takes 93 KB of it).
    assert!(total < 900_000, "fixtures total {total} bytes");
}
