//! LPIPS (Zhang et al. 2018, the `lpips` Python package v0.1) with VGG16 and AlexNet trunks,
//! on the `cpu` and `gpu` backends.
//!
//! The computation, exactly as `lpips.LPIPS(net=..., version="0.1").forward(in0, in1)`:
//! 1. inputs in [-1, 1] (an image in [0, 1] maps by `2x - 1`), NCHW;
//! 2. the scaling layer `(x - shift) / scale` with ImageNet-derived constants;
//! 3. the torchvision feature trunk (conv + ReLU, max pools), tapping five ReLU outputs
//!    (VGG16: relu1_2, relu2_2, relu3_3, relu4_3, relu5_3; AlexNet: relu1..relu5);
//! 4. per tap: unit-normalise each pixel's channel vector (`f / (|f| + 1e-10)`), square the
//!    difference of the two images, weight channels with the 1x1 "lin" layer (no bias) and
//!    average over the pixels;
//! 5. sum the five layer values.
//!
//! Weights come from a safetensors file holding the package's `state_dict()` (names
//! `net.sliceK.I.weight|bias`, `linK.model.1.weight` or `linK.model.0.weight`, optionally
//! `scaling_layer.shift|scale`), written by `tests/lpips/convert_weights.py`. Steps 1, 2 and
//! the spatial average run on the host in both backends; the trunk and step 4's per-pixel
//! map run on the chosen backend ([`cpu`], [`gpu`]).
//!
//! For training, [`Lpips::distances_with_gradient`] also returns the gradient of each pair's
//! distance with respect to its first image (the render); [`LpipsInput`] chooses how images
//! in [0, 1] enter the network (the package's `2x - 1`, or the authors' unmapped quirk).

pub mod cpu;
pub mod gpu;
pub mod seeded;

use std::path::Path;

use crate::backend::{Backend, BackendError};

use crate::image::ImageF32;
use crate::safetensors::{SafetensorsError, SafetensorsFile};
use crate::scalar::Scalar;

/// The ScalingLayer constants of the `lpips` package (v0.1).
pub const SCALING_SHIFT: [f32; 3] = [-0.030, -0.088, -0.188];
pub const SCALING_SCALE: [f32; 3] = [0.458, 0.448, 0.450];

/// `normalize_tensor`'s epsilon, added to the channel norm.
pub const NORM_EPSILON: f32 = 1e-10;

/// Which feature trunk.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LpipsNet {
    Vgg,
    Alex,
}

impl LpipsNet {
    /// Channels of the five tapped layers (`LPIPS.chns`).
    pub fn tap_channels(self) -> [usize; 5] {
        match self {
            Self::Vgg => [64, 128, 256, 512, 512],
            Self::Alex => [64, 192, 384, 256, 256],
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::Vgg => "vgg",
            Self::Alex => "alex",
        }
    }
}

/// A 2D convolution followed by ReLU; `name` is its state-dict prefix.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ConvSpec {
    pub name: String,
    pub in_channels: usize,
    pub out_channels: usize,
    pub kernel: usize,
    pub stride: usize,
    pub padding: usize,
}

impl ConvSpec {
    /// The weight tensor's shape `(out, in, k, k)`.
    pub fn weight_shape(&self) -> [usize; 4] {
        [
            self.out_channels,
            self.in_channels,
            self.kernel,
            self.kernel,
        ]
    }

    /// Output extent along one axis for an input extent (PyTorch's floor formula), or `None`
    /// when the input is smaller than the kernel.
    pub fn output_extent(&self, input: usize) -> Option<usize> {
        let padded = input + 2 * self.padding;
        (padded >= self.kernel).then(|| (padded - self.kernel) / self.stride + 1)
    }
}

/// One step of a trunk, in order.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Step {
    /// Convolution + ReLU.
    Conv(ConvSpec),
    /// Max pool without padding, floor mode.
    MaxPool { kernel: usize, stride: usize },
    /// The current activation is one of the five LPIPS taps.
    Tap,
}

impl Step {
    /// Output extent of a max pool along one axis, `None` when the input is too small.
    pub fn pool_extent(kernel: usize, stride: usize, input: usize) -> Option<usize> {
        (input >= kernel).then(|| (input - kernel) / stride + 1)
    }

    /// The step's output extent along one axis (a tap keeps it), `None` when the input is
    /// smaller than the kernel.
    pub fn extent(&self, input: usize) -> Option<usize> {
        match self {
            Self::Conv(spec) => spec.output_extent(input),
            Self::MaxPool { kernel, stride } => Self::pool_extent(*kernel, *stride, input),
            Self::Tap => Some(input),
        }
    }

    /// What an error about an image too small for the step names.
    fn label(&self) -> &str {
        match self {
            Self::Conv(spec) => &spec.name,
            Self::MaxPool { .. } => "max pool",
            Self::Tap => "tap",
        }
    }
}

fn conv(
    slice: usize,
    index: usize,
    in_channels: usize,
    out_channels: usize,
    kernel: usize,
    stride: usize,
    padding: usize,
) -> Step {
    Step::Conv(ConvSpec {
        name: format!("net.slice{slice}.{index}"),
        in_channels,
        out_channels,
        kernel,
        stride,
        padding,
    })
}

/// The trunk of `net` as in `lpips/pretrained_networks.py` (module indices are torchvision's
/// `features` indices, which the state-dict names keep).
pub fn steps(net: LpipsNet) -> Vec<Step> {
    let pool2 = Step::MaxPool {
        kernel: 2,
        stride: 2,
    };
    let pool3 = Step::MaxPool {
        kernel: 3,
        stride: 2,
    };
    match net {
        LpipsNet::Vgg => vec![
            conv(1, 0, 3, 64, 3, 1, 1),
            conv(1, 2, 64, 64, 3, 1, 1),
            Step::Tap,
            pool2.clone(),
            conv(2, 5, 64, 128, 3, 1, 1),
            conv(2, 7, 128, 128, 3, 1, 1),
            Step::Tap,
            pool2.clone(),
            conv(3, 10, 128, 256, 3, 1, 1),
            conv(3, 12, 256, 256, 3, 1, 1),
            conv(3, 14, 256, 256, 3, 1, 1),
            Step::Tap,
            pool2.clone(),
            conv(4, 17, 256, 512, 3, 1, 1),
            conv(4, 19, 512, 512, 3, 1, 1),
            conv(4, 21, 512, 512, 3, 1, 1),
            Step::Tap,
            pool2,
            conv(5, 24, 512, 512, 3, 1, 1),
            conv(5, 26, 512, 512, 3, 1, 1),
            conv(5, 28, 512, 512, 3, 1, 1),
            Step::Tap,
        ],
        LpipsNet::Alex => vec![
            conv(1, 0, 3, 64, 11, 4, 2),
            Step::Tap,
            pool3.clone(),
            conv(2, 3, 64, 192, 5, 1, 2),
            Step::Tap,
            pool3,
            conv(3, 6, 192, 384, 3, 1, 1),
            Step::Tap,
            conv(4, 8, 384, 256, 3, 1, 1),
            Step::Tap,
            conv(5, 10, 256, 256, 3, 1, 1),
            Step::Tap,
        ],
    }
}

/// Spatial size of every tapped layer for an input of `height x width`, or an error naming
/// the step that the image is too small for.
pub fn tap_sizes(
    net: LpipsNet,
    height: usize,
    width: usize,
) -> Result<Vec<(usize, usize)>, LpipsError> {
    let (mut h, mut w) = (height, width);
    let mut sizes = Vec::new();
    let too_small = |what: &str| LpipsError::Input {
        message: format!(
            "a {height} x {width} image is too small for the {} trunk ({what})",
            net.name()
        ),
    };
    for step in steps(net) {
        if step == Step::Tap {
            sizes.push((h, w));
            continue;
        }
        (h, w) = match (step.extent(h), step.extent(w)) {
            (Some(h), Some(w)) => (h, w),
            _ => return Err(too_small(step.label())),
        };
    }
    Ok(sizes)
}

/// Why LPIPS could not be computed.
#[derive(Debug, thiserror::Error)]
pub enum LpipsError {
    #[error(transparent)]
    File(#[from] SafetensorsError),
    #[error("{path}: LPIPS {net} weights: {message}")]
    Weights {
        path: String,
        net: &'static str,
        message: String,
    },
    #[error("LPIPS input: {message}")]
    Input { message: String },
    /// The cause is in the message, so it is not also a `source` (chains would repeat it).
    #[error("LPIPS on the gpu: {0}")]
    Gpu(BackendError),
}

impl From<BackendError> for LpipsError {
    fn from(error: BackendError) -> Self {
        Self::Gpu(error)
    }
}

/// One convolution's parameters: weight `(out, in, k, k)` row-major, bias `(out)`.
#[derive(Clone, Debug, PartialEq)]
pub struct ConvWeights {
    pub spec: ConvSpec,
    pub weight: Vec<f32>,
    pub bias: Vec<f32>,
}

/// All parameters of one LPIPS network.
#[derive(Clone, Debug, PartialEq)]
pub struct LpipsWeights {
    pub net: LpipsNet,
    /// In trunk order.
    pub convs: Vec<ConvWeights>,
    /// The five 1x1 lin layers, one weight per channel.
    pub lins: Vec<Vec<f32>>,
    pub shift: [f32; 3],
    pub scale: [f32; 3],
}

impl LpipsWeights {
    /// Loads `net`'s weights from a safetensors file (see the module docs for the names).
    pub fn load(path: &Path, net: LpipsNet) -> Result<Self, LpipsError> {
        let file = SafetensorsFile::read(path)?;
        Self::from_file(&file, net)
    }

    /// Writes the weights as a safetensors file with the `lpips` package's state-dict names
    /// (what `tests/lpips/convert_weights.py` produces), e.g. for seeded test weights.
    pub fn write_safetensors(&self, path: &Path) -> std::io::Result<()> {
        write_f32_tensors(path, &self.state_dict())
    }

    /// The weights as `(name, shape, values)` in the package's state-dict layout: convs in
    /// trunk order, then the five lin layers, then the scaling layer.
    pub(crate) fn state_dict(&self) -> Vec<(String, Vec<usize>, &[f32])> {
        let mut tensors: Vec<(String, Vec<usize>, &[f32])> = Vec::new();
        for conv in &self.convs {
            let spec = &conv.spec;
            tensors.push((
                format!("{}.weight", spec.name),
                spec.weight_shape().to_vec(),
                &conv.weight,
            ));
            tensors.push((
                format!("{}.bias", spec.name),
                vec![spec.out_channels],
                &conv.bias,
            ));
        }
        for (layer, lin) in self.lins.iter().enumerate() {
            tensors.push((
                format!("lin{layer}.model.1.weight"),
                vec![1, lin.len(), 1, 1],
                lin,
            ));
        }
        tensors.push((
            "scaling_layer.shift".to_owned(),
            vec![1, 3, 1, 1],
            &self.shift,
        ));
        tensors.push((
            "scaling_layer.scale".to_owned(),
            vec![1, 3, 1, 1],
            &self.scale,
        ));
        tensors
    }

    /// Reads `net`'s weights from an opened file; a missing or misshapen tensor is an error
    /// naming the file and the tensor.
    pub fn from_file(file: &SafetensorsFile, net: LpipsNet) -> Result<Self, LpipsError> {
        let mut convs = Vec::new();
        for step in steps(net) {
            if let Step::Conv(spec) = step {
                let weight =
                    file.f32_tensor(&format!("{}.weight", spec.name), &spec.weight_shape())?;
                let bias = file.f32_tensor(&format!("{}.bias", spec.name), &[spec.out_channels])?;
                convs.push(ConvWeights { spec, weight, bias });
            }
        }
        let mut lins = Vec::new();
        for (layer, channels) in net.tap_channels().into_iter().enumerate() {
            // `use_dropout=True` (the default) puts the conv at index 1 of the Sequential.
            let with_dropout = format!("lin{layer}.model.1.weight");
            let without_dropout = format!("lin{layer}.model.0.weight");
            let name = if file.info(&with_dropout).is_some() {
                with_dropout
            } else {
                without_dropout
            };
            lins.push(file.f32_tensor(&name, &[1, channels, 1, 1])?);
        }
        let constant = |name: &str, default: [f32; 3]| -> Result<[f32; 3], LpipsError> {
            if file.info(name).is_none() {
                return Ok(default);
            }
            let values = file.f32_tensor(name, &[1, 3, 1, 1])?;
            Ok([values[0], values[1], values[2]])
        };
        let weights = Self {
            net,
            convs,
            lins,
            shift: constant("scaling_layer.shift", SCALING_SHIFT)?,
            scale: constant("scaling_layer.scale", SCALING_SCALE)?,
        };
        weights.checked(&file.path().display().to_string())
    }

    /// The weights when they [`validate`](Self::validate); else the error, naming `path`.
    fn checked(self, path: &str) -> Result<Self, LpipsError> {
        match self.validate() {
            Ok(()) => Ok(self),
            Err(message) => Err(LpipsError::Weights {
                path: path.to_owned(),
                net: self.net.name(),
                message,
            }),
        }
    }

    /// Checks internal consistency (shapes against the architecture, usable constants).
    pub fn validate(&self) -> Result<(), String> {
        let specs: Vec<ConvSpec> = steps(self.net)
            .into_iter()
            .filter_map(|step| match step {
                Step::Conv(spec) => Some(spec),
                _ => None,
            })
            .collect();
        if specs.len() != self.convs.len() {
            return Err(format!(
                "{} convolutions, expected {}",
                self.convs.len(),
                specs.len()
            ));
        }
        for (spec, conv) in specs.iter().zip(&self.convs) {
            if conv.spec != *spec
                || conv.weight.len() != spec.weight_shape().iter().product::<usize>()
                || conv.bias.len() != spec.out_channels
            {
                return Err(format!(
                    "{}: parameters do not match the architecture",
                    spec.name
                ));
            }
        }
        for (layer, (lin, channels)) in self.lins.iter().zip(self.net.tap_channels()).enumerate() {
            if lin.len() != channels {
                return Err(format!(
                    "lin{layer}: {} weights, expected {channels}",
                    lin.len()
                ));
            }
        }
        if self.lins.len() != 5 {
            return Err(format!("{} lin layers, expected 5", self.lins.len()));
        }
        if self
            .scale
            .iter()
            .any(|scale| !scale.is_finite() || scale.abs() <= 1e-6)
            || self.shift.iter().any(|shift| !shift.is_finite())
        {
            return Err(format!(
                "scaling layer shift {:?} / scale {:?} unusable",
                self.shift, self.scale
            ));
        }
        Ok(())
    }
}

/// Writes little-endian f32 tensors `(name, shape, values)` as a safetensors file.
pub(crate) fn write_f32_tensors(
    path: &Path,
    tensors: &[(String, Vec<usize>, &[f32])],
) -> std::io::Result<()> {
    let bytes: Vec<Vec<u8>> = tensors
        .iter()
        .map(|(_, _, values)| values.iter().flat_map(|v| v.to_le_bytes()).collect())
        .collect();
    let views: Vec<(&str, crate::safetensors::Dtype, &[usize], &[u8])> = tensors
        .iter()
        .zip(&bytes)
        .map(|((name, shape, _), data)| {
            (
                name.as_str(),
                crate::safetensors::Dtype::F32,
                shape.as_slice(),
                data.as_slice(),
            )
        })
        .collect();
    crate::safetensors::write(path, &views, &Default::default())
}

/// An LPIPS value with its five per-layer terms (their sum is `total`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LpipsDistance {
    pub total: f64,
    pub layers: [f64; 5],
}

/// A batch of images in NCHW layout after the scaling layer: the trunk's input.
#[derive(Clone, Debug, PartialEq)]
pub struct TrunkInput {
    pub batch: usize,
    pub height: usize,
    pub width: usize,
    pub data: Vec<f32>,
}

/// Per tapped layer, the per-pixel distance maps of every pair, `(pairs, h, w)` row-major.
pub type DistanceMaps = Vec<Vec<f32>>;

/// How images in [0, 1] enter the network (the package expects [-1, 1]).
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "snake_case")]
pub enum LpipsInput {
    /// Mapped by `2x - 1`: the package's `normalize=True`, the paper's meaning.
    #[default]
    Unit,
    /// Fed unchanged as if they were in [-1, 1]: the authors' training code (docs/method.md,
    /// "inputs in [0,1] without normalisation").
    UnitAsSigned,
}

impl LpipsInput {
    /// `d signed / d unit` of the mapping.
    fn slope<S: Scalar>(self) -> S {
        match self {
            Self::Unit => S::from_f64(2.0),
            Self::UnitAsSigned => S::ONE,
        }
    }

    fn signed<S: Scalar>(self, unit: S) -> S {
        match self {
            Self::Unit => unit * S::from_f64(2.0) - S::ONE,
            Self::UnitAsSigned => unit,
        }
    }
}

/// Writes one `(h, w, 3)` image in [0, 1] as trunk input planes `(3, h, w)`: the input
/// mapping, then the scaling layer `(x - shift) / scale`.
pub fn image_to_trunk<S: Scalar>(
    weights: &LpipsWeights,
    image: &[S],
    input: LpipsInput,
    planes: &mut [S],
) {
    let pixels = image.len() / 3;
    for (pixel, rgb) in image.chunks_exact(3).enumerate() {
        for channel in 0..3 {
            let signed = input.signed(rgb[channel]);
            planes[channel * pixels + pixel] = (signed
                - S::from_f64(f64::from(weights.shift[channel])))
                / S::from_f64(f64::from(weights.scale[channel]));
        }
    }
}

/// The adjoint of [`image_to_trunk`]: a gradient with respect to trunk input planes
/// `(3, h, w)` as one with respect to the image `(h, w, 3)`.
pub fn trunk_gradient_to_image<S: Scalar>(
    weights: &LpipsWeights,
    planes: &[S],
    input: LpipsInput,
) -> Vec<S> {
    let pixels = planes.len() / 3;
    let factors: [S; 3] = std::array::from_fn(|channel| {
        input.slope::<S>() / S::from_f64(f64::from(weights.scale[channel]))
    });
    (0..pixels * 3)
        .map(|index| {
            let (pixel, channel) = (index / 3, index % 3);
            planes[channel * pixels + pixel] * factors[channel]
        })
        .collect()
}

/// Stacks the pairs' first images, then their second images, mapped from [0, 1] by `input`
/// and through the scaling layer (f32 arithmetic, as the package does).
pub fn trunk_input(
    weights: &LpipsWeights,
    pairs: &[(&ImageF32, &ImageF32)],
    input: LpipsInput,
) -> Result<TrunkInput, LpipsError> {
    let Some((first, _)) = pairs.first() else {
        return Err(LpipsError::Input {
            message: "no image pairs".to_owned(),
        });
    };
    let (height, width) = (first.height, first.width);
    for (index, (image0, image1)) in pairs.iter().enumerate() {
        for image in [image0, image1] {
            if image.height != height || image.width != width {
                return Err(LpipsError::Input {
                    message: format!(
                        "pair {index}: image of {} x {}, expected {height} x {width} like pair 0",
                        image.height, image.width
                    ),
                });
            }
        }
    }
    let pixels = height * width;
    let mut data = vec![0.0_f32; 2 * pairs.len() * 3 * pixels];
    let images = pairs
        .iter()
        .map(|pair| pair.0)
        .chain(pairs.iter().map(|pair| pair.1));
    for (slot, image) in images.enumerate() {
        let planes = &mut data[slot * 3 * pixels..(slot + 1) * 3 * pixels];
        image_to_trunk(weights, &image.data, input, planes);
    }
    Ok(TrunkInput {
        batch: 2 * pairs.len(),
        height,
        width,
        data,
    })
}

/// Averages each layer's per-pixel map per pair (in f64) and sums the layers.
pub fn reduce_maps(maps: &DistanceMaps, pairs: usize) -> Vec<LpipsDistance> {
    let mut distances = vec![
        LpipsDistance {
            total: 0.0,
            layers: [0.0; 5],
        };
        pairs
    ];
    for (layer, map) in maps.iter().enumerate() {
        let pixels = map.len() / pairs.max(1);
        for (pair, distance) in distances.iter_mut().enumerate() {
            let sum: f64 = map[pair * pixels..(pair + 1) * pixels]
                .iter()
                .map(|&value| f64::from(value))
                .sum();
            distance.layers[layer] = sum / pixels as f64;
        }
    }
    for distance in &mut distances {
        distance.total = distance.layers.iter().sum();
    }
    distances
}

/// LPIPS ready to run on one backend (weights uploaded once for the gpu).
pub struct Lpips {
    weights: LpipsWeights,
    gpu: Option<gpu::GpuLpips>,
}

impl Lpips {
    pub fn new(weights: LpipsWeights, backend: &Backend) -> Result<Self, LpipsError> {
        let weights = weights.checked("(in memory)")?;
        let gpu = match backend {
            Backend::Cpu => None,
            Backend::Gpu(context) => Some(gpu::GpuLpips::new(context.clone(), &weights)?),
        };
        Ok(Self { weights, gpu })
    }

    pub fn weights(&self) -> &LpipsWeights {
        &self.weights
    }

    /// LPIPS of each pair; all images must have one size.
    pub fn distances(
        &self,
        pairs: &[(&ImageF32, &ImageF32)],
    ) -> Result<Vec<LpipsDistance>, LpipsError> {
        Ok(self.evaluate(pairs, LpipsInput::Unit, false)?.0)
    }

    /// LPIPS of each pair and the gradient of each pair's `total` with respect to its first
    /// image, `(h, w, 3)` row-major like [`ImageF32::data`]; the second images are
    /// constants. All images must have one size, at least the trunk's minimum
    /// ([`tap_sizes`]).
    pub fn distances_with_gradient(
        &self,
        pairs: &[(&ImageF32, &ImageF32)],
        input: LpipsInput,
    ) -> Result<(Vec<LpipsDistance>, Vec<Vec<f32>>), LpipsError> {
        self.evaluate(pairs, input, true)
    }

    /// The distances and, `with_gradient`, the first images' gradients (else none).
    fn evaluate(
        &self,
        pairs: &[(&ImageF32, &ImageF32)],
        input: LpipsInput,
        with_gradient: bool,
    ) -> Result<(Vec<LpipsDistance>, Vec<Vec<f32>>), LpipsError> {
        let Some((first, _)) = pairs.first() else {
            return Ok((Vec::new(), Vec::new()));
        };
        tap_sizes(self.weights.net, first.height, first.width)?;
        let trunk = trunk_input(&self.weights, pairs, input)?;
        let (maps, gradient) = match (&self.gpu, with_gradient) {
            (None, false) => (cpu::distance_maps(&self.weights, &trunk)?, Vec::new()),
            (None, true) => cpu::distance_gradient(&self.weights, &trunk)?,
            (Some(gpu), false) => (gpu.distance_maps(&trunk)?, Vec::new()),
            (Some(gpu), true) => gpu.distance_gradient(&trunk)?,
        };
        let plane_values = 3 * first.height * first.width;
        let gradients = gradient
            .chunks_exact(plane_values)
            .map(|planes| trunk_gradient_to_image(&self.weights, planes, input))
            .collect();
        Ok((reduce_maps(&maps, pairs.len()), gradients))
    }
}

#[cfg(test)]
mod gpu_tests;
#[cfg(test)]
mod tests;
