//! The optimiser pieces against the `cpu` code on a gpu adapter (lavapipe in CI).

use std::sync::Arc;

use seqavatar_compute::backend::test_support::{
    gpu_test_context, gpu_test_context_with_dispatch_limit,
};
use seqavatar_compute::backend::{GpuBuffer, GpuContext};
use seqavatar_compute::nn::adam::{AdamConfig, AdamState, adam_update};

use super::adam::{GaussianAdam, GaussianGradients};
use super::densify::GradientStats;
use super::state::{GaussianRates, OptimiserStep, RECORD_WORDS, ResidentGaussians};
use crate::densify::{GaussianState, names};
use crate::gaussians::{SH, SH_STORED, TRAINABLE, initial_state};
use crate::rng::Rng;
use crate::step::host::update_sh;

/// Values exactly representable in f32, so that both sides start from the same numbers.
fn random(rng: &mut Rng, len: usize, lo: f64, hi: f64) -> Vec<f64> {
    (0..len)
        .map(|_| f64::from(rng.uniform(lo, hi) as f32))
        .collect()
}

/// A state of `n` Gaussians with random parameters, moments and statistics.
fn random_state(rng: &mut Rng, n: usize) -> GaussianState {
    let centres = random(rng, 3 * n, -1.0, 1.0);
    let colours = random(rng, 3 * n, 0.0, 1.0);
    let scales = random(rng, 3 * n, 0.01, 0.1);
    let mut state = initial_state(&centres, &colours, 0.1, &scales).unwrap();
    for column in &mut state.columns {
        let len = column.values.len();
        column.values = match column.name.as_str() {
            name if name.ends_with(".adam_v") => random(rng, len, 0.0, 1e-3),
            name if name.ends_with(".adam_m") => random(rng, len, -1e-2, 1e-2),
            names::GRAD_COUNT => (0..len).map(|i| (i % 4) as f64).collect(),
            _ => random(rng, len, -1.0, 1.0),
        };
    }
    state
}

fn f32s(values: &[f64]) -> Vec<f32> {
    values.iter().map(|&v| v as f32).collect()
}

fn upload(context: &GpuContext, what: &str, values: &[f64]) -> GpuBuffer {
    context.upload(what, &f32s(values)).unwrap()
}

fn assert_close(what: &str, device: &[f64], cpu: &[f64], tolerance: f64) {
    assert_eq!(device.len(), cpu.len(), "{what}: lengths");
    for (i, (d, c)) in device.iter().zip(cpu).enumerate() {
        assert!(
            (d - c).abs() <= tolerance * (1.0 + c.abs()),
            "{what}[{i}]: device {d} cpu {c}"
        );
    }
}

fn rates(iteration: u64) -> GaussianRates {
    let learning_rates = crate::config::LearningRates::default();
    GaussianRates::at(&learning_rates, 1.7, iteration)
}

/// One iteration's gradients, as the backward produces them on the cpu.
struct HostGradients {
    xyz: Vec<f64>,
    log_scale: Vec<f64>,
    rotation: Vec<f64>,
    aiap: [Vec<f64>; 3],
    opacity: Vec<f64>,
    sh: Vec<f64>,
}

fn host_gradients(rng: &mut Rng, n: usize, k: usize) -> HostGradients {
    HostGradients {
        xyz: random(rng, 3 * n, -1e-3, 1e-3),
        log_scale: random(rng, 3 * n, -1e-3, 1e-3),
        rotation: random(rng, 4 * n, -1e-3, 1e-3),
        aiap: [
            random(rng, 3 * n, -1e-4, 1e-4),
            random(rng, 3 * n, -1e-4, 1e-4),
            random(rng, 4 * n, -1e-4, 1e-4),
        ],
        opacity: random(rng, n, -1e-2, 1e-2),
        sh: random(rng, 3 * k * n, -1e-3, 1e-3),
    }
}

/// `Trainer::optimiser_phase` on the Gaussians' columns, with the gradient assembly of
/// `Trainer::backward_phase` (chain rule, SH scatter, AIAP sums).
fn cpu_step(state: &mut GaussianState, g: &HostGradients, with_aiap: bool, step: &OptimiserStep) {
    let n = state.len();
    let k = (step.sh_degree + 1) * (step.sh_degree + 1);
    let add = |a: &[f64], b: &[f64]| -> Vec<f64> {
        if with_aiap {
            a.iter().zip(b).map(|(x, y)| x + y).collect()
        } else {
            a.to_vec()
        }
    };
    let logits = state.values(names::OPACITY_LOGIT).unwrap();
    let d_opacity: Vec<f64> = (0..n)
        .map(|i| {
            let o = 1.0 / (1.0 + (-logits[i]).exp());
            g.opacity[i] * o * (1.0 - o)
        })
        .collect();
    let mut d_sh = vec![0.0; n * 3 * SH_STORED];
    for i in 0..n {
        d_sh[i * 3 * SH_STORED..i * 3 * SH_STORED + 3 * k]
            .copy_from_slice(&g.sh[i * 3 * k..(i + 1) * 3 * k]);
    }
    let gradients = [
        (names::POSITION, add(&g.xyz, &g.aiap[0])),
        (SH, d_sh),
        (names::OPACITY_LOGIT, d_opacity),
        (names::LOG_SCALE, add(&g.log_scale, &g.aiap[1])),
        (names::ROTATION, add(&g.rotation, &g.aiap[2])),
    ];
    for (name, gradient) in gradients {
        let mut moments = AdamState {
            m: std::mem::take(state.values_mut(&format!("{name}.adam_m")).unwrap()),
            v: std::mem::take(state.values_mut(&format!("{name}.adam_v")).unwrap()),
            step: step.adam_step - 1,
        };
        let values = state.values_mut(name).unwrap();
        let r = &step.rates;
        if name == SH {
            update_sh(
                &step.adam,
                r.sh_dc,
                r.sh_rest,
                values,
                &gradient,
                &mut moments,
                n,
            )
            .unwrap();
        } else {
            let rate = match name {
                names::POSITION => r.position,
                names::OPACITY_LOGIT => r.opacity,
                names::LOG_SCALE => r.scaling,
                _ => r.rotation,
            };
            adam_update(&step.adam, rate, values, &gradient, &mut moments).unwrap();
        }
        *state.values_mut(&format!("{name}.adam_m")).unwrap() = moments.m;
        *state.values_mut(&format!("{name}.adam_v")).unwrap() = moments.v;
    }
}

struct DeviceGradients {
    xyz: GpuBuffer,
    log_scale: GpuBuffer,
    rotation: GpuBuffer,
    aiap: [GpuBuffer; 3],
    opacity: GpuBuffer,
    sh: GpuBuffer,
}

impl DeviceGradients {
    fn new(context: &GpuContext, g: &HostGradients) -> Self {
        DeviceGradients {
            xyz: upload(context, "xyz", &g.xyz),
            log_scale: upload(context, "log_scale", &g.log_scale),
            rotation: upload(context, "rotation", &g.rotation),
            aiap: [
                upload(context, "aiap xyz", &g.aiap[0]),
                upload(context, "aiap log_scale", &g.aiap[1]),
                upload(context, "aiap rotation", &g.aiap[2]),
            ],
            opacity: upload(context, "opacity", &g.opacity),
            sh: upload(context, "sh", &g.sh),
        }
    }

    fn view(&self, with_aiap: bool) -> GaussianGradients<'_> {
        GaussianGradients {
            xyz: &self.xyz,
            log_scale: &self.log_scale,
            rotation: &self.rotation,
            opacity: &self.opacity,
            sh: &self.sh,
            aiap: with_aiap.then(|| [&self.aiap[0], &self.aiap[1], &self.aiap[2]]),
        }
    }
}

fn step(iteration: u64, sh_degree: usize) -> OptimiserStep {
    OptimiserStep {
        iteration,
        adam_step: iteration,
        adam: AdamConfig::default(),
        rates: rates(iteration),
        sh_degree,
        half_size: 256.0,
    }
}

fn download(gaussians: &ResidentGaussians, like: &GaussianState) -> GaussianState {
    let mut state = like.clone();
    gaussians.download_into(&mut state).unwrap();
    state
}

fn adam_matches_cpu_on(context: &Arc<GpuContext>, n: usize) {
    let mut rng = Rng::new(3);
    let mut cpu = random_state(&mut rng, n);
    let mut gaussians = ResidentGaussians::upload(context, &cpu).unwrap();
    let adam = GaussianAdam::new(context).unwrap();
    // Degree 0 and 3, the schedule's first iterations and one past its end, with and
    // without AIAP.
    for (iteration, degree, with_aiap) in [
        (1, 0, true),
        (2, 0, false),
        (3, 1, true),
        (4, 3, true),
        (40_000, 3, true),
    ] {
        let s = step(iteration, degree);
        let k = (degree + 1) * (degree + 1);
        let host = host_gradients(&mut rng, n, k);
        let device = DeviceGradients::new(context, &host);
        gaussians.write_step(&s).unwrap();
        let mut encoder = context.encoder();
        adam.record(&mut encoder, &gaussians, &device.view(with_aiap), degree)
            .unwrap();
        context.submit_and_wait(encoder).unwrap();
        cpu_step(&mut cpu, &host, with_aiap, &s);
        let got = download(&gaussians, &cpu);
        for (name, _) in TRAINABLE {
            for suffix in ["", ".adam_m", ".adam_v"] {
                let full = format!("{name}{suffix}");
                assert_close(
                    &format!("iteration {iteration}: {full}"),
                    got.values(&full).unwrap(),
                    cpu.values(&full).unwrap(),
                    2e-5,
                );
            }
        }
        // Continue from the device's (f32) state on both sides.
        cpu = got;
        gaussians.reupload(&cpu).unwrap();
    }
    assert_eq!(gaussians.download_status().unwrap(), None);
}

#[test]
fn adam_matches_cpu_over_steps_with_schedules_and_sh_degrees() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    // Not a multiple of the workgroup; and one Gaussian.
    adam_matches_cpu_on(&context, 301);
    adam_matches_cpu_on(&context, 1);
    // Every dispatch split into a 2D grid.
    let Some(limited) = gpu_test_context_with_dispatch_limit(3) else {
        return;
    };
    adam_matches_cpu_on(&limited, 1000);
}

/// The status's first non-finite value: (iteration, "parameter" or "gradient of", tensor,
/// Gaussian).
fn assert_flagged(gaussians: &ResidentGaussians, expected: (u64, &str, &str, usize)) {
    let found = gaussians.download_status().unwrap().expect("flagged");
    assert_eq!(
        (
            found.iteration,
            found.what,
            found.tensor.as_str(),
            found.gaussian
        ),
        expected
    );
}

#[test]
fn non_finite_gradients_and_values_are_flagged_with_the_first_iteration_and_gaussian() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    let n = 40;
    let mut rng = Rng::new(5);
    let mut state = random_state(&mut rng, n);
    // A non-finite rotation value of Gaussian 11 (its gradient is finite).
    state.values_mut(names::ROTATION).unwrap()[4 * 11 + 2] = f64::INFINITY;
    let mut gaussians = ResidentGaussians::upload(&context, &state).unwrap();
    let adam = GaussianAdam::new(&context).unwrap();
    let run = |gaussians: &ResidentGaussians, iteration: u64, host: &HostGradients| {
        gaussians.write_step(&step(iteration, 3)).unwrap();
        let device = DeviceGradients::new(&context, host);
        let mut encoder = context.encoder();
        adam.record(&mut encoder, gaussians, &device.view(true), 3)
            .unwrap();
        context.submit_and_wait(encoder).unwrap();
    };
    run(&gaussians, 1, &host_gradients(&mut rng, n, 16));
    assert_flagged(&gaussians, (1, "parameter", "gaussians/rotation", 11));
    // Gradients: NaN in the SH of Gaussians 30 and 9, infinite AIAP xyz of Gaussian 17.
    state.values_mut(names::ROTATION).unwrap()[4 * 11 + 2] = 0.5;
    gaussians = ResidentGaussians::upload(&context, &state).unwrap();
    let mut host = host_gradients(&mut rng, n, 16);
    host.sh[48 * 30 + 7] = f64::NAN;
    host.sh[48 * 9 + 40] = f64::NAN;
    host.aiap[0][3 * 17 + 1] = f64::INFINITY;
    run(&gaussians, 7, &host);
    assert_flagged(&gaussians, (7, "gradient of", "gaussians/xyz", 17));
    // A later iteration with an earlier Gaussian does not replace the first report.
    let mut later = host_gradients(&mut rng, n, 16);
    later.xyz[0] = f64::NAN;
    run(&gaussians, 8, &later);
    let mut words = context
        .download::<u32>(context.encoder(), &gaussians.status().buffer, 20)
        .unwrap();
    let found = ResidentGaussians::decode_status(&words).unwrap();
    assert_eq!((found.iteration, found.gaussian), (7, 17));
    // The SH slot holds iteration 7's smallest Gaussian.
    assert_eq!(
        (u32::MAX - words[2], u32::MAX - words[3]),
        (7, 9),
        "sh gradient slot"
    );
    words.iter_mut().for_each(|w| *w = 0);
    assert_eq!(ResidentGaussians::decode_status(&words), None);
}

#[test]
fn densification_statistics_match_the_cpu() {
    let Some(context) = gpu_test_context_with_dispatch_limit(2) else {
        return;
    };
    let n = 700;
    let mut rng = Rng::new(8);
    let mut cpu = random_state(&mut rng, n);
    let gaussians = ResidentGaussians::upload(&context, &cpu).unwrap();
    let stats = GradientStats::new(&context).unwrap();
    for iteration in 1..=3 {
        let s = OptimiserStep {
            half_size: 100.0 * iteration as f64,
            ..step(iteration, 0)
        };
        // About a third invisible (0), one NaN.
        let mut norms: Vec<f64> = random(&mut rng, n, -1e-3, 2e-3)
            .into_iter()
            .map(|v| v.max(0.0))
            .collect();
        norms[5] = f64::NAN;
        let device_norms = upload(&context, "mean_2d_norm", &norms);
        gaussians.write_step(&s).unwrap();
        let mut encoder = context.encoder();
        stats
            .record(&mut encoder, &gaussians, &device_norms)
            .unwrap();
        context.submit_and_wait(encoder).unwrap();
        let scaled: Vec<f64> = norms.iter().map(|g| g * s.half_size).collect();
        let visible: Vec<bool> = norms.iter().map(|g| *g > 0.0).collect();
        cpu.accumulate_gradient_stats(&scaled, &visible).unwrap();
    }
    let got = download(&gaussians, &cpu);
    assert_close(
        "grad_accum",
        got.values(names::GRAD_ACCUM).unwrap(),
        cpu.values(names::GRAD_ACCUM).unwrap(),
        1e-6,
    );
    assert_eq!(
        got.values(names::GRAD_COUNT).unwrap(),
        cpu.values(names::GRAD_COUNT).unwrap()
    );
}

#[test]
fn upload_download_round_trip_and_growth() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    let mut rng = Rng::new(11);
    let state = random_state(&mut rng, 50);
    let mut gaussians = ResidentGaussians::upload(&context, &state).unwrap();
    assert_eq!(gaussians.len(), 50);
    assert!(gaussians.capacity() >= 75);
    // The state's values are f32-exact: the round trip is the identity.
    assert_eq!(download(&gaussians, &state), state);
    // Fewer Gaussians (pruned): the same buffers.
    let small = random_state(&mut rng, 20);
    assert!(!gaussians.reupload(&small).unwrap());
    assert_eq!(download(&gaussians, &small), small);
    // More than the capacity (densified): new buffers, grown.
    let large = random_state(&mut rng, 400);
    assert!(gaussians.reupload(&large).unwrap());
    assert!(gaussians.capacity() >= 400);
    assert_eq!(download(&gaussians, &large), large);
    // A state without a trainable moment is refused, naming it.
    let mut missing = large.clone();
    missing.columns.retain(|c| c.name != "sh.adam_v");
    let error = ResidentGaussians::upload(&context, &missing).unwrap_err();
    assert!(format!("{error:#}").contains("sh.adam_v"), "{error:#}");
    // A state whose extra column does not match the count is refused on download.
    let mut extra = small.clone();
    extra
        .add(
            "knn_template",
            2,
            crate::densify::Growth::Inherit,
            vec![0.0; 40],
        )
        .unwrap();
    assert!(gaussians.download_into(&mut extra).is_err());
}

#[test]
fn a_steady_state_step_uploads_only_its_record_and_reads_nothing_back() {
    // A context of its own: the shared one counts the other tests' traffic too.
    let Some(context) = gpu_test_context_with_dispatch_limit(65535) else {
        return;
    };
    let n = 500;
    let mut rng = Rng::new(2);
    let state = random_state(&mut rng, n);
    let gaussians = ResidentGaussians::upload(&context, &state).unwrap();
    let adam = GaussianAdam::new(&context).unwrap();
    let stats = GradientStats::new(&context).unwrap();
    let device = DeviceGradients::new(&context, &host_gradients(&mut rng, n, 16));
    let norms = upload(&context, "norms", &random(&mut rng, n, 0.0, 1e-3));
    let iterate = |iteration: u64| {
        gaussians.write_step(&step(iteration, 3)).unwrap();
        let mut encoder = context.encoder();
        stats.record(&mut encoder, &gaussians, &norms).unwrap();
        adam.record(&mut encoder, &gaussians, &device.view(true), 3)
            .unwrap();
        context.submit_and_wait(encoder).unwrap();
    };
    iterate(1);
    let before = context.transfers();
    for iteration in 2..=4 {
        iterate(iteration);
    }
    let traffic = context.transfers().since(&before);
    assert_eq!(traffic.readbacks, 0, "{traffic:?}");
    assert_eq!(traffic.bytes_down, 0, "{traffic:?}");
    assert_eq!(traffic.bytes_up, 3 * 4 * RECORD_WORDS as u64, "{traffic:?}");
}

// ---------------------------------------------------------------------------------------
// AIAP

use super::aiap::ResidentAiap;
use crate::losses::{AiapGaussians, AiapWeights, aiap_gaussians};
use seqavatar_compute::backend::shaders::AtomicAdd;
use seqavatar_knn::{MovingKnn, as_points, knn_brute_force};

/// Points on a lattice of step 1/8 (distances exact in f32, many ties), some coincident.
fn lattice_points(rng: &mut Rng, n: usize) -> Vec<f64> {
    let mut xyz: Vec<f64> = (0..3 * n).map(|_| rng.below(9) as f64 / 8.0).collect();
    for i in (5..n).step_by(7) {
        let (from, to) = (3 * (i - 3), 3 * i);
        xyz.copy_within(from..from + 3, to);
    }
    xyz
}

fn state_with_centres(rng: &mut Rng, xyz: &[f64]) -> GaussianState {
    let mut state = random_state(rng, xyz.len() / 3);
    *state.values_mut(names::POSITION).unwrap() = xyz.to_vec();
    state
}

fn aiap_neighbours_on(context: &Arc<GpuContext>, xyz: &[f64], k: usize) -> Vec<u32> {
    let n = xyz.len() / 3;
    let mut rng = Rng::new(1);
    let gaussians = ResidentGaussians::upload(context, &state_with_centres(&mut rng, xyz)).unwrap();
    let weights = AiapWeights {
        centre: 1.0,
        covariance: 0.0,
        neighbours: k,
    };
    let mut aiap = ResidentAiap::new(context, weights).unwrap();
    let centres = upload(context, "deformed centres", xyz);
    let covariances = upload(context, "deformed covariances", &vec![0.0; 6 * n]);
    let mut encoder = context.encoder();
    aiap.record(&mut encoder, &gaussians, &centres, &covariances)
        .unwrap();
    context.submit_and_wait(encoder).unwrap();
    aiap.download_neighbours(n).unwrap()
}

#[test]
fn neighbours_match_moving_knn_ties_and_duplicates_included() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    let mut rng = Rng::new(4);
    for (n, k) in [(300, 5), (37, 16), (257, 1), (4, 4), (2, 2)] {
        let xyz = lattice_points(&mut rng, n);
        let expected = MovingKnn::default().neighbours(&as_points(&xyz), k);
        assert_eq!(
            aiap_neighbours_on(&context, &xyz, k),
            expected,
            "{n} points, k = {k}"
        );
    }
    // Random f32 points: the brute force on the same values.
    let xyz = random(&mut rng, 3 * 1000, -1.0, 1.0);
    let points = as_points(&xyz);
    assert_eq!(
        aiap_neighbours_on(&context, &xyz, 5),
        knn_brute_force(&points, &points, 5)
    );
    // 2D grids.
    let Some(limited) = gpu_test_context_with_dispatch_limit(2) else {
        return;
    };
    let xyz = lattice_points(&mut rng, 900);
    assert_eq!(
        aiap_neighbours_on(&limited, &xyz, 5),
        MovingKnn::default().neighbours(&as_points(&xyz), 5)
    );
}

struct AiapCase {
    state: GaussianState,
    deformed_centres: Vec<f64>,
    deformed_covariances: Vec<f64>,
}

/// Gaussians on a lattice (ties, coincident pairs), one degenerate quaternion, deformed by
/// an affine map plus noise.
fn aiap_case(rng: &mut Rng, n: usize) -> AiapCase {
    let xyz = lattice_points(rng, n);
    let mut state = state_with_centres(rng, &xyz);
    *state.values_mut(names::LOG_SCALE).unwrap() = random(rng, 3 * n, -4.0, -2.0);
    if n > 3 {
        state.values_mut(names::ROTATION).unwrap()[12..16].copy_from_slice(&[0.0; 4]);
    }
    let noise = random(rng, 3 * n, -0.02, 0.02);
    let deformed_centres = xyz
        .iter()
        .zip(&noise)
        .map(|(x, e)| f64::from((1.2 * x + 0.1 + e) as f32))
        .collect();
    let deformed_covariances = random(rng, 6 * n, -1e-3, 1e-3);
    AiapCase {
        state,
        deformed_centres,
        deformed_covariances,
    }
}

fn assert_close_scaled(what: &str, device: &[f64], cpu: &[f64], tolerance: f64) {
    let scale = cpu.iter().fold(0.0_f64, |m, v| m.max(v.abs())).max(1e-30);
    assert_eq!(device.len(), cpu.len(), "{what}: lengths");
    for (i, (d, c)) in device.iter().zip(cpu).enumerate() {
        assert!(
            (d - c).abs() <= tolerance * scale,
            "{what}[{i}]: device {d} cpu {c} (largest {scale})"
        );
    }
}

fn aiap_matches_cpu_on(context: &Arc<GpuContext>, mode: AtomicAdd, n: usize, neighbours: usize) {
    let mut rng = Rng::new(n as u64 + 17);
    let case = aiap_case(&mut rng, n);
    let weights = AiapWeights {
        centre: 1.0,
        covariance: 100.0,
        neighbours,
    };
    let gaussians = ResidentGaussians::upload(context, &case.state).unwrap();
    let mut aiap = ResidentAiap::with_atomic_add(context, weights, mode).unwrap();
    let centres = upload(context, "deformed centres", &case.deformed_centres);
    let covariances = upload(context, "deformed covariances", &case.deformed_covariances);
    // Twice: the second call must not add onto the first's gradients.
    for _ in 0..2 {
        let mut encoder = context.encoder();
        aiap.record(&mut encoder, &gaussians, &centres, &covariances)
            .unwrap();
        context.submit_and_wait(encoder).unwrap();
    }
    let s = &case.state;
    let cpu = aiap_gaussians(
        &AiapGaussians {
            xyz: s.values(names::POSITION).unwrap(),
            log_scale: s.values(names::LOG_SCALE).unwrap(),
            rotation: s.values(names::ROTATION).unwrap(),
            deformed_centres: &case.deformed_centres,
            deformed_covariances: &case.deformed_covariances,
        },
        weights,
        &mut MovingKnn::default(),
    )
    .expect("active");
    let log = aiap.download_log().unwrap();
    let what = format!("{n} Gaussians, k {neighbours}, {mode:?}");
    assert!(
        (f64::from(log[0]) - cpu.value).abs() <= 1e-5 * cpu.value,
        "{what}: value {} cpu {}",
        log[0],
        cpu.value
    );
    let g = aiap.gradients().unwrap();
    let read = |buffer: &GpuBuffer, len: usize| -> Vec<f64> {
        context
            .download::<f32>(context.encoder(), &buffer.buffer, len)
            .unwrap()
            .into_iter()
            .map(f64::from)
            .collect()
    };
    for (name, device, width, want) in [
        ("xyz", &g.xyz, 3, &cpu.xyz),
        ("log_scale", &g.log_scale, 3, &cpu.log_scale),
        ("rotation", &g.rotation, 4, &cpu.rotation),
        (
            "deformed centres",
            &g.deformed_centres,
            3,
            &cpu.deformed_centres,
        ),
        (
            "deformed covariances",
            &g.deformed_covariances,
            6,
            &cpu.deformed_covariances,
        ),
    ] {
        assert_close_scaled(
            &format!("{what}: {name}"),
            &read(device, width * n),
            want,
            1e-4,
        );
    }
}

#[test]
fn aiap_value_and_gradients_match_the_cpu_with_both_atomic_adds() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    let mut modes = vec![AtomicAdd::CompareExchange];
    if context.has_float_atomics() {
        modes.push(AtomicAdd::NativeFloat);
    }
    for mode in modes {
        // Not a multiple of the workgroup; k larger than N - 1 (k = N).
        aiap_matches_cpu_on(&context, mode, 300, 5);
        aiap_matches_cpu_on(&context, mode, 3, 5);
        aiap_matches_cpu_on(&context, mode, 2, 5);
    }
    let Some(limited) = gpu_test_context_with_dispatch_limit(2) else {
        return;
    };
    aiap_matches_cpu_on(&limited, AtomicAdd::CompareExchange, 700, 5);
}

#[test]
fn aiap_off_records_zeros_and_costs_no_traffic_in_the_steady_state() {
    let Some(context) = gpu_test_context_with_dispatch_limit(65535) else {
        return;
    };
    let mut rng = Rng::new(6);
    let case = aiap_case(&mut rng, 200);
    let gaussians = ResidentGaussians::upload(&context, &case.state).unwrap();
    let centres = upload(&context, "deformed centres", &case.deformed_centres);
    let covariances = upload(&context, "deformed covariances", &case.deformed_covariances);
    let on = AiapWeights {
        centre: 1.0,
        covariance: 100.0,
        neighbours: 5,
    };
    let mut aiap = ResidentAiap::new(&context, on).unwrap();
    let run = |aiap: &mut ResidentAiap| {
        let mut encoder = context.encoder();
        aiap.record(&mut encoder, &gaussians, &centres, &covariances)
            .unwrap();
        context.submit_and_wait(encoder).unwrap();
    };
    run(&mut aiap);
    let before = context.transfers();
    run(&mut aiap);
    run(&mut aiap);
    let traffic = context.transfers().since(&before);
    assert_eq!(
        (traffic.readbacks, traffic.bytes_up, traffic.bytes_down),
        (0, 0, 0)
    );
    assert!(aiap.download_log().unwrap()[0] > 0.0);
    // Off: zero log and gradients, even after an active call.
    let mut off = ResidentAiap::new(
        &context,
        AiapWeights {
            centre: 0.0,
            covariance: 0.0,
            neighbours: 5,
        },
    )
    .unwrap();
    run(&mut off);
    assert_eq!(off.download_log().unwrap(), [0.0; 3]);
    let g = off.gradients().unwrap();
    let d = context
        .download::<f32>(context.encoder(), &g.deformed_covariances.buffer, 6 * 200)
        .unwrap();
    assert!(d.iter().all(|v| *v == 0.0));
    assert!(!off.active(200) && aiap.active(200) && !aiap.active(1));
    // k above what the kernel holds is refused, naming the field.
    let error = ResidentAiap::new(
        &context,
        AiapWeights {
            neighbours: 17,
            ..on
        },
    )
    .unwrap_err();
    assert!(error.to_string().contains("aiap_neighbours"), "{error}");
}

/// Gaussians moving a little every iteration (and once far): every iteration's neighbours
/// are `MovingKnn`'s, the device rebuilt its lists only sometimes, and a call makes no
/// transfer.
#[test]
fn verlet_lists_follow_moving_gaussians_exactly_and_rebuild_only_when_needed() {
    let Some(context) = gpu_test_context_with_dispatch_limit(2) else {
        return;
    };
    let n = 600;
    let k = 5;
    let mut rng = Rng::new(12);
    let mut xyz = random(&mut rng, 3 * n, -1.0, 1.0);
    let mut state = state_with_centres(&mut rng, &xyz);
    let mut gaussians = ResidentGaussians::upload(&context, &state).unwrap();
    let weights = AiapWeights {
        centre: 1.0,
        covariance: 100.0,
        neighbours: k,
    };
    let mut aiap = ResidentAiap::new(&context, weights).unwrap();
    let centres = upload(&context, "deformed centres", &vec![0.0; 3 * n]);
    let covariances = upload(&context, "deformed covariances", &vec![0.0; 6 * n]);
    let mut knn = MovingKnn::default();
    let mut traffic = seqavatar_compute::backend::Transfers::default();
    for iteration in 0..12 {
        // Small steps (a fraction of the spacing), one large jump of a single Gaussian.
        let step = if iteration == 8 { 0.0 } else { 2e-3 };
        for v in &mut xyz {
            *v = f64::from((*v + rng.uniform(-step, step)) as f32);
        }
        if iteration == 8 {
            xyz[3 * 17] = 0.9;
        }
        *state.values_mut(names::POSITION).unwrap() = xyz.clone();
        gaussians.reupload(&state).unwrap();
        let before = context.transfers();
        let mut encoder = context.encoder();
        aiap.record(&mut encoder, &gaussians, &centres, &covariances)
            .unwrap();
        context.queue().submit([encoder.finish()]);
        if iteration > 0 {
            let t = context.transfers().since(&before);
            traffic.readbacks += t.readbacks;
            traffic.bytes_up += t.bytes_up;
        }
        let expected = knn.neighbours(&as_points(&xyz), k);
        assert_eq!(
            aiap.download_neighbours(n).unwrap(),
            expected,
            "iteration {iteration}"
        );
    }
    assert_eq!((traffic.readbacks, traffic.bytes_up), (0, 0));
    let (rebuilds, calls) = aiap.download_searches().unwrap();
    assert_eq!(calls, 12);
    assert!(
        (2..12).contains(&rebuilds),
        "{rebuilds} full searches in {calls} calls"
    );
    // A count change invalidates the lists.
    let fewer = &xyz[..3 * (n - 50)];
    let state = state_with_centres(&mut rng, fewer);
    gaussians.reupload(&state).unwrap();
    let mut encoder = context.encoder();
    aiap.record(&mut encoder, &gaussians, &centres, &covariances)
        .unwrap();
    context.submit_and_wait(encoder).unwrap();
    assert_eq!(
        aiap.download_neighbours(n - 50).unwrap(),
        MovingKnn::default().neighbours(&as_points(fewer), k)
    );
    assert_eq!(aiap.download_searches().unwrap().0, rebuilds + 1);
}

/// What a full neighbour search costs next to an iteration that reuses the Verlet lists
/// (`cargo test -p seqavatar-train --lib --release resident::tests::aiap_cost -- --ignored
/// --nocapture`; prints milliseconds per call, set `AIAP_COST_N` for the count).
#[test]
#[ignore = "timing, run by hand"]
fn aiap_cost_of_a_full_search_and_of_a_reused_list() {
    let Some(context) = gpu_test_context() else {
        return;
    };
    let n: usize = std::env::var("AIAP_COST_N")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(8192);
    let mut rng = Rng::new(13);
    let case = aiap_case(&mut rng, n);
    let mut state = case.state;
    *state.values_mut(names::POSITION).unwrap() = random(&mut rng, 3 * n, -1.0, 1.0);
    let gaussians = ResidentGaussians::upload(&context, &state).unwrap();
    let centres = upload(&context, "deformed centres", &case.deformed_centres);
    let covariances = upload(&context, "deformed covariances", &case.deformed_covariances);
    let weights = AiapWeights {
        centre: 1.0,
        covariance: 100.0,
        neighbours: 5,
    };
    let mut aiap = ResidentAiap::new(&context, weights).unwrap();
    let time = |aiap: &mut ResidentAiap| {
        let start = std::time::Instant::now();
        let mut encoder = context.encoder();
        aiap.record(&mut encoder, &gaussians, &centres, &covariances)
            .unwrap();
        context.submit_and_wait(encoder).unwrap();
        start.elapsed().as_secs_f64() * 1e3
    };
    let full = time(&mut aiap);
    let reused: f64 = (0..5).map(|_| time(&mut aiap)).sum::<f64>() / 5.0;
    let (rebuilds, calls) = aiap.download_searches().unwrap();
    eprintln!(
        "AIAP at {n} Gaussians on {}: {full:.2} ms with a full search, {reused:.2} ms reusing the lists ({rebuilds} searches in {calls} calls)",
        context.describe()
    );
    assert_eq!((rebuilds, calls), (1, 6));
}
