//! One description per network: input blocks, dense layers (what each reads, its width,
//! activation and initialisation) and the output, built from [`NetworkConfig`]; the `cpu`
//! interpreter ([`super::network::Network`], generic over f32/f64) and the `gpu` one
//! ([`super::gpu::GpuNetworks`]) both run a network from its [`NetworkSpec`] and nothing
//! else, so a block or a layer is added in one place: the builder of its network
//! ([`NetworkSpec::non_rigid`], [`NetworkSpec::pose_refiner`], [`NetworkSpec::lbs_offsets`]).
//!
//! # Rows
//!
//! Every value (an input block or a layer output) lives in one of four row spaces
//! ([`Rows`]): one row per frame, `L` rows per frame (a window of `L` elements), one row per
//! Gaussian (`n` rows), or one row per Gaussian and window element (`L` blocks of `n` rows).
//! A layer runs in one row space and reads:
//!
//! - values of its own row space (a windowed layer reads element `l` of a windowed value in
//!   its `l`-th product);
//! - per-Gaussian values from a per-Gaussian-window layer: the same rows for every element,
//!   their gradient summed over the elements;
//! - per-frame values from a per-Gaussian layer, as the last column blocks of its input: they
//!   are never copied to every Gaussian. Their product with their rows of the weight, plus
//!   the bias, is one per-frame bias of the per-Gaussian product (identical maths), and its
//!   gradient is the column sum;
//! - [`Source::Window`]: the `L` elements of a windowed layer's output side by side as the
//!   column blocks of a non-windowed layer's input (the flattening of the window; one block
//!   of `L w` columns for a per-frame window, whose elements are contiguous).
//!
//! Weight rows follow the order of the layer's sources; parameter names are
//! `{prefix}.{layer name}.weight` and `.bias` ([`NetworkSpec::parameter_name`]).

use seqavatar_compute::nn::{Activation, LinearShape, NnScalar, PositionalEncoding};

use super::dense::Init;
use super::{HEAD_WIDTH, ModelError, NetworkConfig, NetworkGroup, check_finite, check_input};

/// Bound of the uniform initialisation of the body-pose refiner's last layer.
pub const LAST_LAYER_BOUND: f64 = 1e-5;

/// The row space of a value or a layer (see the module documentation).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Rows {
    /// One row per frame.
    Frame,
    /// `L` rows per frame, one per window element, contiguous (`L x width`).
    FrameWindow,
    /// One row per Gaussian (`n x width`).
    Gaussian,
    /// One row per Gaussian and window element. Given as `n x L x width`; evaluated as `L`
    /// blocks of `n x width`.
    GaussianWindow,
}

impl Rows {
    /// Whether the rows are per Gaussian.
    pub fn per_gaussian(self) -> bool {
        matches!(self, Rows::Gaussian | Rows::GaussianWindow)
    }

    /// Number of products a layer in this row space runs per pass (`L` for a per-Gaussian
    /// window, whose elements are separate blocks; else 1).
    pub fn calls(self, window: usize) -> usize {
        match self {
            Rows::GaussianWindow => window,
            _ => 1,
        }
    }

    /// Rows of one block (one product) with `n` Gaussians and window length `window`.
    pub fn block_rows(self, n: usize, window: usize) -> usize {
        match self {
            Rows::Frame => 1,
            Rows::FrameWindow => window,
            Rows::Gaussian | Rows::GaussianWindow => n,
        }
    }
}

/// One input block of a network.
#[derive(Clone, Debug, PartialEq)]
pub struct InputSpec {
    /// The field name errors use (e.g. `gaussians.xyz`).
    pub name: String,
    /// Its row space.
    pub rows: Rows,
    /// Values per row as given.
    pub width: usize,
    /// The positional encoding applied before any layer reads it.
    pub encoding: Option<PositionalEncoding>,
    /// Whether the backward returns its gradient (else it is data, or detached).
    pub gradient: bool,
}

impl InputSpec {
    /// Values per row as the layers read it (after the encoding).
    pub fn value_width(&self) -> usize {
        match self.encoding {
            Some(encoding) => encoding.out_features(self.width),
            None => self.width,
        }
    }
}

/// What a layer reads, one column block (or, for [`Source::Window`], `L` of them) each.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Source {
    /// An input block (encoded if it has an encoding).
    Input(usize),
    /// The output of an earlier layer.
    Layer(usize),
    /// The `L` window elements of an earlier windowed layer's output, side by side.
    Window(usize),
}

impl Source {
    /// The window elements of a layer's output side by side ([`Source::Window`]); other
    /// sources are returned unchanged (and a description reading them is still checked).
    pub fn window(self) -> Source {
        match self {
            Source::Layer(j) => Source::Window(j),
            other => other,
        }
    }
}

/// One dense layer `act(concat(sources) W + b)`.
#[derive(Clone, Debug, PartialEq)]
pub struct LayerSpec {
    /// Name within the network (e.g. `trunk.0`).
    pub name: String,
    /// The row space it runs in.
    pub rows: Rows,
    /// Its input's column blocks, in weight-row order.
    pub sources: Vec<Source>,
    /// Output width.
    pub out: usize,
    pub activation: Activation,
    pub init: Init,
}

/// One network: inputs, layers in evaluation (and initialisation) order, output layer.
#[derive(Clone, Debug, PartialEq)]
pub struct NetworkSpec {
    /// Prefix of the parameter names (e.g. `non_rigid`).
    pub prefix: String,
    /// The optimiser group of every layer.
    pub group: NetworkGroup,
    /// Window length `L` of the windowed row spaces.
    pub window: usize,
    /// Input blocks, in the order the interpreters take them.
    pub inputs: Vec<InputSpec>,
    /// Layers; each reads only inputs and earlier layers.
    pub layers: Vec<LayerSpec>,
    /// The layer whose output is the network's output.
    pub output: usize,
}

/// A value a layer reads or writes: an input block or a layer output.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Value {
    Input(usize),
    Layer(usize),
}

/// One column block of one product: `block` of `value`, `cols` wide.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Part {
    pub(crate) value: Value,
    pub(crate) block: usize,
    pub(crate) cols: usize,
}

/// The column blocks of one product of a layer: those with the layer's rows, then the
/// per-frame ones folded into a per-frame bias (empty unless the layer is per Gaussian and
/// reads per-frame values).
#[derive(Clone, Debug, Default, PartialEq)]
pub(crate) struct Plan {
    pub(crate) rows: Vec<Part>,
    pub(crate) frame: Vec<Part>,
}

impl Part {
    /// The block this part reads, from the per-value blocks of the inputs and the layers.
    pub(crate) fn pick<'a, T>(&self, inputs: &'a [Vec<T>], outputs: &'a [Vec<T>]) -> &'a T {
        let blocks = match self.value {
            Value::Input(i) => &inputs[i],
            Value::Layer(j) => &outputs[j],
        };
        &blocks[self.block]
    }
}

impl Plan {
    /// Width of the parts with the layer's rows (the leading weight rows).
    pub(crate) fn rows_in(&self) -> usize {
        self.rows.iter().map(|p| p.cols).sum()
    }

    /// Width of the folded per-frame parts (the trailing weight rows).
    pub(crate) fn frame_in(&self) -> usize {
        self.frame.iter().map(|p| p.cols).sum()
    }
}

impl NetworkSpec {
    /// An empty network.
    pub fn new(prefix: &str, group: NetworkGroup, window: usize) -> Self {
        NetworkSpec {
            prefix: prefix.into(),
            group,
            window,
            inputs: Vec::new(),
            layers: Vec::new(),
            output: 0,
        }
    }

    /// Adds an input block; returns its source handle.
    pub fn input(
        &mut self,
        name: &str,
        rows: Rows,
        width: usize,
        encoding: Option<PositionalEncoding>,
        gradient: bool,
    ) -> Source {
        self.inputs.push(InputSpec {
            name: name.into(),
            rows,
            width,
            encoding,
            gradient,
        });
        Source::Input(self.inputs.len() - 1)
    }

    /// Adds a layer (PyTorch-default initialisation); returns its source handle. The last
    /// layer added is the output unless [`NetworkSpec::output`] is set afterwards.
    pub fn layer(
        &mut self,
        name: &str,
        rows: Rows,
        sources: &[Source],
        out: usize,
        activation: Activation,
    ) -> Source {
        self.layer_with_init(name, rows, sources, out, activation, Init::PytorchDefault)
    }

    /// [`NetworkSpec::layer`] with another initialisation.
    pub fn layer_with_init(
        &mut self,
        name: &str,
        rows: Rows,
        sources: &[Source],
        out: usize,
        activation: Activation,
        init: Init,
    ) -> Source {
        self.layers.push(LayerSpec {
            name: name.into(),
            rows,
            sources: sources.to_vec(),
            out,
            activation,
            init,
        });
        self.output = self.layers.len() - 1;
        Source::Layer(self.output)
    }

    /// The non-rigid network (`motion_context` not `none`): see [`super`] for the blocks.
    /// Trunk input order: per-Gaussian blocks (encoding, seq-xyz), then per-frame blocks
    /// (pose, seq-pose).
    pub fn non_rigid(config: &NetworkConfig) -> Self {
        let w = &config.widths;
        let relu = Activation::Relu;
        let length = config.sequence_length;
        let mut net = NetworkSpec::new("non_rigid", NetworkGroup::NonRigid, length);
        let pose = net.input(
            "frame.local_pose",
            Rows::Frame,
            config.pose_dim(),
            None,
            false,
        );
        let motion = config.motion_context.has_skeleton_motion().then(|| {
            net.input(
                "frame.skeleton_motion",
                Rows::FrameWindow,
                config.seq_pose_row(),
                None,
                false,
            )
        });
        let xyz = net.input("gaussians.xyz", Rows::Gaussian, 3, Some(w.encoding()), true);
        let velocity = config.motion_context.has_velocity().then(|| {
            net.input(
                "gaussians.knn_velocity",
                Rows::GaussianWindow,
                config.seq_xyz_row(),
                None,
                false,
            )
        });
        let pose_hidden = net.layer("pose_encoder.0", Rows::Frame, &[pose], w.pose_encoder, relu);
        let pose_out = net.layer(
            "pose_encoder.1",
            Rows::Frame,
            &[pose_hidden],
            w.pose_encoder,
            relu,
        );
        let seq_pose = motion.map(|motion| {
            let frames = net.layer(
                "seq_pose_encoder.frame",
                Rows::FrameWindow,
                &[motion],
                w.seq_pose_frame,
                relu,
            );
            net.layer(
                "seq_pose_encoder.sequence",
                Rows::Frame,
                &[frames.window()],
                w.seq_pose,
                relu,
            )
        });
        let seq_xyz = velocity.map(|velocity| {
            let v = net.layer(
                "seq_xyz_encoder.velocity",
                Rows::GaussianWindow,
                &[velocity],
                w.seq_xyz_velocity,
                relu,
            );
            let p = net.layer(
                "seq_xyz_encoder.position",
                Rows::Gaussian,
                &[xyz],
                w.seq_xyz_position,
                relu,
            );
            let frames = net.layer(
                "seq_xyz_encoder.frame",
                Rows::GaussianWindow,
                &[v, p],
                w.seq_xyz_frame,
                relu,
            );
            let hidden = net.layer(
                "seq_xyz_encoder.sequence.0",
                Rows::Gaussian,
                &[frames.window()],
                w.seq_xyz_hidden,
                relu,
            );
            net.layer(
                "seq_xyz_encoder.sequence.1",
                Rows::Gaussian,
                &[hidden],
                w.seq_xyz,
                relu,
            )
        });
        let trunk_in: Vec<Source> = [Some(xyz), seq_xyz, Some(pose_out), seq_pose]
            .into_iter()
            .flatten()
            .collect();
        let mut previous = net.layer(
            "trunk.0",
            Rows::Gaussian,
            &trunk_in,
            config.trunk_width,
            relu,
        );
        for index in 1..config.trunk_depth {
            previous = net.layer(
                &format!("trunk.{index}"),
                Rows::Gaussian,
                &[previous],
                config.trunk_width,
                relu,
            );
        }
        net.layer(
            "heads",
            Rows::Gaussian,
            &[previous],
            HEAD_WIDTH,
            Activation::Identity,
        );
        net
    }

    /// The body-pose refiner: `3 (J - 1) -> hidden -> hidden -> 3 (J - 1)`, the last layer
    /// `U(+-1e-5)` with zero bias.
    pub fn pose_refiner(config: &NetworkConfig) -> Self {
        let pose = config.pose_dim();
        let hidden = config.widths.pose_refiner_hidden;
        let relu = Activation::Relu;
        let mut net = NetworkSpec::new("pose_refiner", NetworkGroup::PoseRefiner, 1);
        let input = net.input("local_pose", Rows::Frame, pose, None, false);
        let h0 = net.layer("0", Rows::Frame, &[input], hidden, relu);
        let h1 = net.layer("1", Rows::Frame, &[h0], hidden, relu);
        net.layer_with_init(
            "2",
            Rows::Frame,
            &[h1],
            pose,
            Activation::Identity,
            Init::SmallUniform(LAST_LAYER_BOUND),
        );
        net
    }

    /// The LBS-offset network: encoding (detached) `-> h -> h -> h`, skip
    /// `concat(h, encoding) -> h -> J`.
    pub fn lbs_offsets(config: &NetworkConfig) -> Self {
        let w = &config.widths;
        let hidden = w.lbs_hidden;
        let relu = Activation::Relu;
        let mut net = NetworkSpec::new("lbs_offsets", NetworkGroup::LbsOffsets, 1);
        let xyz = net.input("lbs xyz", Rows::Gaussian, 3, Some(w.encoding()), false);
        let h0 = net.layer("0", Rows::Gaussian, &[xyz], hidden, relu);
        let h1 = net.layer("1", Rows::Gaussian, &[h0], hidden, relu);
        let h2 = net.layer("2", Rows::Gaussian, &[h1], hidden, relu);
        let h3 = net.layer("3", Rows::Gaussian, &[h2, xyz], hidden, relu);
        net.layer(
            "4",
            Rows::Gaussian,
            &[h3],
            config.skinning_joints,
            Activation::Identity,
        );
        net
    }

    /// `{prefix}.{layer name}`: the stable name of layer `index` (parameters append
    /// `.weight` / `.bias`).
    pub fn parameter_name(&self, index: usize) -> String {
        format!("{}.{}", self.prefix, self.layers[index].name)
    }

    /// The row space of a value.
    pub(crate) fn value_rows(&self, value: Value) -> Rows {
        match value {
            Value::Input(i) => self.inputs[i].rows,
            Value::Layer(j) => self.layers[j].rows,
        }
    }

    /// The width of one row of a value.
    pub(crate) fn value_width(&self, value: Value) -> usize {
        match value {
            Value::Input(i) => self.inputs[i].value_width(),
            Value::Layer(j) => self.layers[j].out,
        }
    }

    /// Input width of layer `index` (the sum of its sources' widths).
    pub fn in_features(&self, index: usize) -> usize {
        self.layers[index]
            .sources
            .iter()
            .map(|&source| match source {
                Source::Input(i) => self.inputs[i].value_width(),
                Source::Layer(j) => self.layers[j].out,
                Source::Window(j) => self.window * self.layers[j].out,
            })
            .sum()
    }

    /// The shape of layer `index`.
    pub fn shape(&self, index: usize) -> LinearShape {
        LinearShape {
            in_features: self.in_features(index),
            out_features: self.layers[index].out,
            activation: self.layers[index].activation,
        }
    }

    /// The column blocks of product `call` of layer `index` (a valid description).
    pub(crate) fn plan(&self, index: usize, call: usize) -> Plan {
        let layer = &self.layers[index];
        let mut plan = Plan::default();
        for &source in &layer.sources {
            let (value, window) = match source {
                Source::Input(i) => (Value::Input(i), false),
                Source::Layer(j) => (Value::Layer(j), false),
                Source::Window(j) => (Value::Layer(j), true),
            };
            let rows = self.value_rows(value);
            let cols = self.value_width(value);
            if window && rows == Rows::GaussianWindow {
                plan.rows
                    .extend((0..self.window).map(|block| Part { value, block, cols }));
            } else if window {
                plan.rows.push(Part {
                    value,
                    block: 0,
                    cols: self.window * cols,
                });
            } else if rows == Rows::Frame && layer.rows.per_gaussian() {
                plan.frame.push(Part {
                    value,
                    block: 0,
                    cols,
                });
            } else {
                let block = if rows == Rows::GaussianWindow {
                    call
                } else {
                    0
                };
                plan.rows.push(Part { value, block, cols });
            }
        }
        plan
    }

    /// Checks the description: sources exist and come before their reader, row spaces are
    /// compatible, folded per-frame sources come last, every layer but the output is read,
    /// widths are positive.
    pub fn validate(&self) -> Result<(), ModelError> {
        let bad = |field: String, message: String| Err(ModelError::Config { field, message });
        if self.layers.is_empty() {
            return bad(self.prefix.clone(), "has no layers".into());
        }
        if self.output >= self.layers.len() {
            return bad(
                format!("{}.output", self.prefix),
                format!("layer {} of {}", self.output, self.layers.len()),
            );
        }
        if self.layers[self.output].rows.calls(self.window) != 1 {
            return bad(
                format!("{}.output", self.prefix),
                "the output layer cannot be per window element".into(),
            );
        }
        let windowed = self
            .inputs
            .iter()
            .map(|i| i.rows)
            .chain(self.layers.iter().map(|l| l.rows))
            .any(|rows| matches!(rows, Rows::FrameWindow | Rows::GaussianWindow));
        if windowed && self.window == 0 {
            return bad(
                format!("{}.window", self.prefix),
                "windowed blocks need a window length >= 1".into(),
            );
        }
        for input in &self.inputs {
            if input.width == 0 {
                return bad(input.name.clone(), "an input needs width >= 1".into());
            }
            if input.gradient && input.rows == Rows::GaussianWindow {
                return bad(
                    input.name.clone(),
                    "a per-Gaussian window input cannot return a gradient".into(),
                );
            }
        }
        let mut read = vec![false; self.layers.len()];
        for (index, layer) in self.layers.iter().enumerate() {
            let field = self.parameter_name(index);
            if layer.out == 0 || layer.sources.is_empty() {
                return bad(field, "a layer needs an output width and sources".into());
            }
            let mut folded = false;
            for (position, &source) in layer.sources.iter().enumerate() {
                if layer.sources[..position].contains(&source) {
                    return bad(field, format!("reads {source:?} twice"));
                }
                let rows = match source {
                    Source::Input(i) if i < self.inputs.len() => self.inputs[i].rows,
                    Source::Layer(j) | Source::Window(j) if j < index => {
                        read[j] = true;
                        self.layers[j].rows
                    }
                    _ => return bad(field, format!("{source:?} is not an earlier block")),
                };
                let fits = match source {
                    Source::Window(_) => matches!(
                        (rows, layer.rows),
                        (Rows::FrameWindow, Rows::Frame) | (Rows::GaussianWindow, Rows::Gaussian)
                    ),
                    _ => {
                        rows == layer.rows
                            || (rows, layer.rows) == (Rows::Gaussian, Rows::GaussianWindow)
                            || (rows == Rows::Frame && layer.rows == Rows::Gaussian)
                    }
                };
                if !fits {
                    return bad(
                        field,
                        format!("a {:?} layer cannot read {source:?} ({rows:?})", layer.rows),
                    );
                }
                let is_folded = rows == Rows::Frame && layer.rows.per_gaussian();
                if folded && !is_folded {
                    return bad(
                        field,
                        "per-frame sources of a per-Gaussian layer must come last".into(),
                    );
                }
                folded |= is_folded;
            }
        }
        if let Some(index) = (0..self.layers.len()).find(|&j| !read[j] && j != self.output) {
            return bad(self.parameter_name(index), "is never read".into());
        }
        Ok(())
    }

    /// The number of Gaussians `n` of `inputs` (0 when no input is per Gaussian), after
    /// checking every input's length and that every value is finite; errors name the input.
    pub(crate) fn check_inputs<S: NnScalar>(&self, inputs: &[&[S]]) -> Result<usize, ModelError> {
        if inputs.len() != self.inputs.len() {
            return Err(ModelError::Input {
                field: format!("{} inputs", self.prefix),
                message: format!(
                    "expected {} blocks, got {}",
                    self.inputs.len(),
                    inputs.len()
                ),
            });
        }
        let mut n = 0;
        if let Some((spec, data)) = self
            .inputs
            .iter()
            .zip(inputs)
            .find(|(spec, _)| spec.rows.per_gaussian())
        {
            let row =
                spec.width * spec.rows.block_rows(1, self.window) * spec.rows.calls(self.window);
            if !data.len().is_multiple_of(row) {
                return Err(ModelError::Input {
                    field: spec.name.clone(),
                    message: format!(
                        "{} values is not a whole number of {row}-vectors",
                        data.len()
                    ),
                });
            }
            n = data.len() / row;
        }
        for (spec, data) in self.inputs.iter().zip(inputs) {
            let expected =
                spec.width * spec.rows.block_rows(n, self.window) * spec.rows.calls(self.window);
            check_input(&spec.name, expected, data.len())?;
        }
        for (spec, data) in self.inputs.iter().zip(inputs) {
            check_finite(&spec.name, data)?;
        }
        Ok(n)
    }

    /// Forward FLOPs (2 per multiply-add) of one pass with `n` Gaussians: every product of
    /// every layer, a per-Gaussian layer's folded per-frame columns counted once (one row).
    pub fn forward_flops(&self, n: usize) -> f64 {
        (0..self.layers.len())
            .map(|index| {
                let layer = &self.layers[index];
                let plan = self.plan(index, 0);
                let rows = layer.rows.block_rows(n, self.window) as f64;
                let calls = layer.rows.calls(self.window) as f64;
                let out = layer.out as f64;
                2.0 * (calls * rows * plan.rows_in() as f64 + plan.frame_in() as f64) * out
            })
            .sum()
    }
}

/// The `L` blocks (`n x width` each) of a per-Gaussian window given as `n x L x width`.
pub(crate) fn window_blocks<S: Copy>(data: &[S], window: usize, width: usize) -> Vec<Vec<S>> {
    let n = data.len() / (window * width).max(1);
    let mut blocks: Vec<Vec<S>> = (0..window).map(|_| Vec::with_capacity(n * width)).collect();
    for gaussian in data.chunks_exact(window * width) {
        for (element, block) in gaussian.chunks_exact(width).zip(&mut blocks) {
            block.extend_from_slice(element);
        }
    }
    blocks
}
