//! A loose skirt whose lower rows follow a damped mass-spring simulation driven by the body.
//!
//! The top ring is sewn to the waist and skinned like the nearest body vertex. The other
//! particles move by Verlet integration with velocity damping and gravity; springs between
//! ring neighbours, row neighbours, diagonals and every second row are enforced as
//! position-based distance constraints with a stiffness per iteration, and particles are
//! pushed out of the pelvis, thigh and shin capsules of the posed body. Because particles
//! carry momentum, the same pose gives different skirt shapes after walking, turning or a
//! sudden stop.
//!
//! The history scene's skirt is a damped oscillator instead ([`SwingParams`], [`Swing`]):
//! the rest skirt carried by the pose, bent by a pendulum driven by the pelvis's motion.

use seqavatar_core::body::BodyModel;
use seqavatar_core::body::procedural::{Part, parts};
use seqavatar_core::glam::{DAffine3, DQuat, DVec2, DVec3};

/// Particles around the skirt.
pub const AROUND: usize = 40;
/// Rows from the waist (row 0, attached) to the hem.
pub const ROWS: usize = 10;
/// Gravity (m/s^2, -y).
const GRAVITY: f64 = 9.81;
/// Fraction of velocity lost per second.
const DAMPING_PER_SECOND: f64 = 1.2;
/// Constraint iterations per substep and stiffness per iteration.
const ITERATIONS: usize = 8;
const STIFFNESS: f64 = 0.9;
/// Clearance kept between the skirt and the body capsules (m).
const CLEARANCE: f64 = 0.015;
/// Joints whose capsules collide with the skirt: pelvis, hips (thighs), knees (shins), spine1.
const COLLIDING_JOINTS: [usize; 6] = [0, 1, 2, 3, 4, 5];

/// The skirt's rest geometry and its simulation state.
pub struct Skirt {
    /// Rest positions in the body's rest (template) space.
    rest: Vec<DVec3>,
    /// Per attached particle (row 0): skinning weights copied from the nearest body vertex.
    attach_weights: Vec<Vec<(usize, f64)>>,
    springs: Vec<(u32, u32, f64)>,
    colliders: Vec<Part>,
    position: Vec<DVec3>,
    previous: Vec<DVec3>,
}

/// Index of the particle at `row`, `around`.
pub fn particle(row: usize, around: usize) -> usize {
    row * AROUND + around % AROUND
}

/// Triangles of the skirt surface (two per quad, wrapping around).
pub fn triangles() -> Vec<[u32; 3]> {
    let mut faces = Vec::with_capacity(2 * AROUND * (ROWS - 1));
    for row in 0..ROWS - 1 {
        for k in 0..AROUND {
            let a = particle(row, k) as u32;
            let b = particle(row, k + 1) as u32;
            let c = particle(row + 1, k + 1) as u32;
            let d = particle(row + 1, k) as u32;
            faces.push([a, d, c]);
            faces.push([a, c, b]);
        }
    }
    faces
}

/// Texture coordinates of each particle: (around in [0, 1), down in [0, 1], 0).
pub fn texture_coordinates() -> Vec<DVec3> {
    (0..ROWS)
        .flat_map(|row| {
            (0..AROUND).map(move |k| {
                DVec3::new(
                    k as f64 / AROUND as f64,
                    row as f64 / (ROWS - 1) as f64,
                    0.0,
                )
            })
        })
        .collect()
}

impl Skirt {
    /// A skirt from the waist (y = 0 in the template) down to above the knees, for a body
    /// whose template (rest, shaped) vertices are `shaped`.
    pub fn new(model: &BodyModel, shaped: &[DVec3], scale: f64) -> Self {
        let mut rest = Vec::with_capacity(AROUND * ROWS);
        for row in 0..ROWS {
            let s = row as f64 / (ROWS - 1) as f64;
            let y = (0.0 - 0.42 * s) * scale;
            let (rx, rz) = (0.205 + 0.1 * s, 0.135 + 0.15 * s);
            for k in 0..AROUND {
                let angle = std::f64::consts::TAU * k as f64 / AROUND as f64;
                rest.push(DVec3::new(
                    rx * scale * angle.sin(),
                    y,
                    rz * scale * angle.cos(),
                ));
            }
        }
        let attach_weights = (0..AROUND)
            .map(|k| {
                let p = rest[particle(0, k)];
                let nearest = (0..shaped.len())
                    .min_by(|&a, &b| {
                        (shaped[a] - p)
                            .length_squared()
                            .total_cmp(&(shaped[b] - p).length_squared())
                    })
                    .expect("the body has vertices");
                model.vertex_weights(nearest).collect()
            })
            .collect();
        let mut springs = Vec::new();
        let mut spring = |a: usize, b: usize| {
            springs.push((a as u32, b as u32, (rest[a] - rest[b]).length()));
        };
        for row in 0..ROWS {
            for k in 0..AROUND {
                spring(particle(row, k), particle(row, k + 1));
                // Bending along the ring keeps the A-line flare from folding flat.
                spring(particle(row, k), particle(row, k + 2));
                if row + 1 < ROWS {
                    spring(particle(row, k), particle(row + 1, k));
                    spring(particle(row, k), particle(row + 1, k + 1));
                    spring(particle(row, k + 1), particle(row + 1, k));
                }
                if row + 2 < ROWS {
                    spring(particle(row, k), particle(row + 2, k));
                }
            }
        }
        let colliders = parts()
            .into_iter()
            .filter(|p| COLLIDING_JOINTS.contains(&p.joint))
            .map(|p| Part {
                a: p.a * scale,
                b: p.b * scale,
                ra: p.ra * scale,
                rb: p.rb * scale,
                ..p
            })
            .collect();
        Self {
            position: rest.clone(),
            previous: rest.clone(),
            rest,
            attach_weights,
            springs,
            colliders,
        }
    }

    /// Places every particle at its rest position carried by the pose (no velocity).
    pub fn reset(&mut self, joint_transforms: &[DAffine3], world: DAffine3) {
        self.position = self.carried(joint_transforms, world);
        self.previous.clone_from(&self.position);
    }

    /// The rest skirt carried by a pose: every particle skinned with the weights of its
    /// column's waist attachment, then moved by `world`. The swinging garment of the history
    /// scene ([`Swing`]) hangs in this shape when its oscillator is at rest.
    pub fn carried(&self, joint_transforms: &[DAffine3], world: DAffine3) -> Vec<DVec3> {
        self.rest
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let blended = blend(&self.attach_weights[i % AROUND], joint_transforms);
                world.transform_point3(blended.transform_point3(*p))
            })
            .collect()
    }

    /// Advances the simulation by `dt` seconds to the body pose given by its skinning
    /// transforms and world transform.
    pub fn step(&mut self, joint_transforms: &[DAffine3], world: DAffine3, dt: f64) {
        let keep = (-DAMPING_PER_SECOND * dt).exp();
        for i in 0..self.position.len() {
            if i < AROUND {
                let blended = blend(&self.attach_weights[i], joint_transforms);
                self.previous[i] = self.position[i];
                self.position[i] = world.transform_point3(blended.transform_point3(self.rest[i]));
                continue;
            }
            let velocity = (self.position[i] - self.previous[i]) * keep;
            self.previous[i] = self.position[i];
            self.position[i] += velocity - DVec3::Y * (GRAVITY * dt * dt);
        }
        let colliders: Vec<(DVec3, DVec3, f64, f64)> = self
            .colliders
            .iter()
            .map(|c| {
                let t = world * joint_transforms[c.joint];
                (t.transform_point3(c.a), t.transform_point3(c.b), c.ra, c.rb)
            })
            .collect();
        for iteration in 0..ITERATIONS {
            // Alternate the sweep direction so Gauss-Seidel ordering does not twist the skirt.
            let forward = iteration % 2 == 0;
            for index in 0..self.springs.len() {
                let index = if forward {
                    index
                } else {
                    self.springs.len() - 1 - index
                };
                let (a, b, rest_length) = self.springs[index];
                let (a, b) = (a as usize, b as usize);
                let delta = self.position[b] - self.position[a];
                let length = delta.length();
                if length < 1e-12 {
                    continue;
                }
                let correction = delta * ((length - rest_length) / length * STIFFNESS);
                // Attached particles do not move; the free end takes the whole correction.
                match (a < AROUND, b < AROUND) {
                    (true, true) => {}
                    (true, false) => self.position[b] -= correction,
                    (false, true) => self.position[a] += correction,
                    (false, false) => {
                        self.position[a] += correction * 0.5;
                        self.position[b] -= correction * 0.5;
                    }
                }
            }
            for p in self.position[AROUND..].iter_mut() {
                for &(a, b, ra, rb) in &colliders {
                    let ab = b - a;
                    let t = ((*p - a).dot(ab) / ab.length_squared()).clamp(0.0, 1.0);
                    let closest = a + ab * t;
                    let radius = ra + (rb - ra) * t + CLEARANCE;
                    let offset = *p - closest;
                    let distance = offset.length();
                    if distance < radius && distance > 1e-9 {
                        *p = closest + offset * (radius / distance);
                    }
                }
            }
        }
    }

    pub fn positions(&self) -> &[DVec3] {
        &self.position
    }
}

/// The skirt of the history scene as a damped oscillator driven by the body's motion.
///
/// The skirt hangs from the waist like a stiffened pendulum: its hem deflection `u`
/// (horizontal, world x and z) is a damped oscillator of natural frequency `omega` whose
/// pivot (the pelvis) moves with velocity `v` and acceleration `a`, with air drag on the
/// hem's velocity `v + u'`:
///
/// `u'' = -omega^2 u - 2 zeta omega u' - a - drag (v + u')`,
///
/// and the skirt twists about the vertical axis by `phi`, a damped torsional oscillator
/// driven by the heading's angular acceleration `psi''`:
///
/// `phi'' = -omega_t^2 phi - 2 zeta_t omega_t phi' - psi''`.
///
/// So the skirt lags behind an acceleration, overshoots and settles while the body holds a
/// pose, and tilts back by `drag v / omega^2` at a steady walking speed `v`. At rest
/// (`u = u' = phi = phi' = 0`) the skirt is its static drape, [`Skirt::carried`];
/// [`Swing::apply`] turns every row about the waist centre by its fraction of the swing
/// angle `|u| / length` and of the twist.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SwingParams {
    /// Hem distance below the waist (m): a deflection `u` turns the hem by `|u| / length`.
    pub length: f64,
    /// Natural frequency of the swing (Hz; a free pendulum of `length` would swing at
    /// `sqrt(g / length) / 2 pi`, the cloth's stiffness raises it) and its damping ratio.
    pub swing_hz: f64,
    pub damping_ratio: f64,
    /// Air drag on the hem's velocity (1/s).
    pub drag_per_second: f64,
    /// Natural frequency of the twist (Hz) and its damping ratio.
    pub twist_hz: f64,
    pub twist_damping_ratio: f64,
}

impl SwingParams {
    /// The history scene's skirt.
    pub const HISTORY: Self = Self {
        length: 0.45,
        swing_hz: 1.2,
        damping_ratio: 0.1,
        drag_per_second: 1.0,
        twist_hz: 1.2,
        twist_damping_ratio: 0.1,
    };

    /// Natural angular frequency of the swing (rad/s).
    pub fn omega(&self) -> f64 {
        std::f64::consts::TAU * self.swing_hz
    }
}

/// The oscillator state of [`SwingParams`]: hem deflection and twist, with their rates.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Swing {
    /// Horizontal hem deflection (world x, z), metres, and its rate.
    pub offset: DVec2,
    pub velocity: DVec2,
    /// Twist about the vertical axis (radians) and its rate.
    pub twist: f64,
    pub twist_rate: f64,
}

impl Swing {
    /// Advances the state by `dt` (semi-implicit Euler) under the pivot's horizontal
    /// velocity and acceleration and the heading's angular acceleration.
    pub fn step(
        &mut self,
        params: &SwingParams,
        pivot_velocity: DVec2,
        pivot_acceleration: DVec2,
        heading_acceleration: f64,
        dt: f64,
    ) {
        let omega = params.omega();
        let acceleration = -self.offset * (omega * omega)
            - self.velocity * (2.0 * params.damping_ratio * omega)
            - pivot_acceleration
            - (pivot_velocity + self.velocity) * params.drag_per_second;
        self.velocity += acceleration * dt;
        self.offset += self.velocity * dt;
        let omega_t = std::f64::consts::TAU * params.twist_hz;
        let twist_acceleration = -self.twist * (omega_t * omega_t)
            - self.twist_rate * (2.0 * params.twist_damping_ratio * omega_t)
            - heading_acceleration;
        self.twist_rate += twist_acceleration * dt;
        self.twist += self.twist_rate * dt;
    }

    /// The state as seen from the body: the hem deflection and its rate along the body's
    /// forward and across axes ([`super::history::heading_axes`] of `heading`), then the
    /// twist and its rate:
    /// `[forward, across, forward rate, across rate, twist, twist rate]` in metres, metres
    /// per second, radians and radians per second. The same skirt shape relative to the body
    /// gives the same values whichever way the body faces.
    pub fn in_body_frame(&self, heading: f64) -> [f64; crate::GARMENT_STATE_COMPONENTS] {
        let (forward, across) = super::history::heading_axes(heading);
        [
            self.offset.dot(forward),
            self.offset.dot(across),
            self.velocity.dot(forward),
            self.velocity.dot(across),
            self.twist,
            self.twist_rate,
        ]
    }

    /// The swinging skirt from its static drape (one position per particle, row-major as
    /// [`particle`]): row `r` turns about the waist centre by the fraction `r / (ROWS - 1)` of
    /// the twist (about +y) and of the swing (the rotation that moves the downward direction
    /// towards the deflection by `|offset| / length` radians). Row 0 (sewn to the waist)
    /// stays; a state at rest returns the drape unchanged.
    pub fn apply(&self, params: &SwingParams, drape: &[DVec3]) -> Vec<DVec3> {
        let centre = drape[..AROUND].iter().copied().sum::<DVec3>() / AROUND as f64;
        let deflection = DVec3::new(self.offset.x, 0.0, self.offset.y);
        // (-y) x u / length: rotating -y about it moves it towards u by |u| / length.
        let swing_axis = DVec3::NEG_Y.cross(deflection) / params.length;
        drape
            .iter()
            .enumerate()
            .map(|(i, &p)| {
                let row = i / AROUND;
                if row == 0 {
                    return p;
                }
                let s = row as f64 / (ROWS - 1) as f64;
                let twist = DQuat::from_rotation_y(self.twist * s);
                let swing = DQuat::from_scaled_axis(swing_axis * s);
                centre + swing * (twist * (p - centre))
            })
            .collect()
    }
}

fn blend(weights: &[(usize, f64)], joint_transforms: &[DAffine3]) -> DAffine3 {
    let mut m = seqavatar_core::glam::DMat3::ZERO;
    let mut t = DVec3::ZERO;
    for &(j, w) in weights {
        m += joint_transforms[j].matrix3 * w;
        t += joint_transforms[j].translation * w;
    }
    DAffine3::from_mat3_translation(m, t)
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_core::body::procedural::procedural_body;

    fn rest_state() -> (BodyModel, Vec<DVec3>, Vec<DAffine3>) {
        let model = procedural_body(0.03);
        let params = model.zero_params();
        let shaped = model.shaped_vertices(&params);
        let rest_joints = model.regress_joints(&shaped);
        let transforms = model.joint_transforms(&rest_joints, &params.pose);
        (model, shaped, transforms)
    }

    #[test]
    fn skirt_is_a_closed_ring_strip_at_rest() {
        let faces = triangles();
        assert_eq!(faces.len(), 2 * AROUND * (ROWS - 1));
        // Every interior edge is shared by two triangles with opposite directions.
        let mut edges = std::collections::HashMap::new();
        for f in &faces {
            for k in 0..3 {
                *edges.entry((f[k], f[(k + 1) % 3])).or_insert(0) += 1;
            }
        }
        assert!(edges.values().all(|&c| c == 1));
        let boundary = edges
            .keys()
            .filter(|(a, b)| !edges.contains_key(&(*b, *a)))
            .count();
        assert_eq!(boundary, 2 * AROUND);
    }

    #[test]
    fn hanging_skirt_stays_put_and_moving_skirt_lags_behind() {
        let (model, shaped, transforms) = rest_state();
        let mut skirt = Skirt::new(&model, &shaped, 1.0);
        let world = DAffine3::IDENTITY;
        skirt.reset(&transforms, world);
        let dt = 1.0 / 240.0;
        for _ in 0..960 {
            skirt.step(&transforms, world, dt);
        }
        // Standing still, the skirt settles: another half second changes it little, the
        // springs keep their lengths and the hem keeps most of its flare.
        let settled = skirt.positions().to_vec();
        for _ in 0..120 {
            skirt.step(&transforms, world, dt);
        }
        let drift = settled
            .iter()
            .zip(skirt.positions())
            .map(|(a, b)| (*a - *b).length())
            .fold(0.0, f64::max);
        assert!(drift < 0.01, "still moving by {drift} m");
        for &(a, b, rest) in &skirt.springs {
            let length = (skirt.positions()[a as usize] - skirt.positions()[b as usize]).length();
            assert!(
                (length / rest - 1.0).abs() < 0.1,
                "spring {a}-{b}: {length} vs {rest}"
            );
        }
        let hem_radius = (0..AROUND)
            .map(|k| {
                let p = skirt.positions()[particle(ROWS - 1, k)];
                (p.x * p.x + p.z * p.z).sqrt()
            })
            .sum::<f64>()
            / AROUND as f64;
        assert!(hem_radius > 0.22, "hem radius {hem_radius}");
        // Accelerate the body along +z: the hem lags behind the waist, then springs back.
        let mut offset = 0.0;
        let mut max_lag: f64 = 0.0;
        for step in 0..240 {
            if step < 60 {
                offset += 1.5 * dt;
            }
            let moved = DAffine3::from_translation(DVec3::new(0.0, 0.0, offset));
            skirt.step(&transforms, moved, dt);
            let hem_z = (0..AROUND)
                .map(|k| skirt.positions()[particle(ROWS - 1, k)].z)
                .sum::<f64>()
                / AROUND as f64;
            max_lag = max_lag.max(offset - hem_z);
        }
        assert!(max_lag > 0.01, "lag {max_lag}");
        // Every particle is outside the thighs after settling.
        for p in &skirt.positions()[AROUND..] {
            assert!(p.is_finite());
        }
    }

    /// The swing integrator against the closed forms of the damped oscillator: free decay
    /// `u(t) = u0 e^(-zeta' w t) (cos(w_d t) + zeta' w / w_d sin(w_d t))` with the drag
    /// folded into the damping, the steady deflections `-a / w^2` under a constant pivot
    /// acceleration and `-drag v / w^2` at a constant pivot velocity, and the twist's decay.
    #[test]
    fn swing_matches_the_damped_oscillator_closed_forms() {
        let params = SwingParams::HISTORY;
        let w = params.omega();
        let c = 2.0 * params.damping_ratio * w + params.drag_per_second;
        let zeta = c / (2.0 * w);
        let wd = w * (1.0 - zeta * zeta).sqrt();
        let dt = 1.0 / 4800.0;
        let mut swing = Swing {
            offset: DVec2::new(0.1, -0.05),
            twist: 0.2,
            ..Default::default()
        };
        let wt = std::f64::consts::TAU * params.twist_hz;
        let zt = params.twist_damping_ratio;
        let wtd = wt * (1.0 - zt * zt).sqrt();
        for step in 1..=4800 {
            swing.step(&params, DVec2::ZERO, DVec2::ZERO, 0.0, dt);
            let t = step as f64 * dt;
            if step % 480 == 0 {
                let shape =
                    (-zeta * w * t).exp() * ((wd * t).cos() + zeta * w / wd * (wd * t).sin());
                let expected = DVec2::new(0.1, -0.05) * shape;
                assert!(
                    (swing.offset - expected).length() < 2e-3 * 0.1,
                    "t {t}: {} vs {expected}",
                    swing.offset
                );
                let twist = 0.2
                    * (-zt * wt * t).exp()
                    * ((wtd * t).cos() + zt * wt / wtd * (wtd * t).sin());
                assert!(
                    (swing.twist - twist).abs() < 2e-3 * 0.2,
                    "t {t}: twist {} vs {twist}",
                    swing.twist
                );
            }
        }
        // Constant pivot acceleration and velocity: the deflection settles at the closed form.
        let (a, v) = (DVec2::new(0.8, 0.0), DVec2::new(0.0, 1.2));
        let mut swing = Swing::default();
        for _ in 0..(20.0 / dt) as usize {
            swing.step(&params, v, a, 0.0, dt);
        }
        let expected = -(a + v * params.drag_per_second) / (w * w);
        assert!(
            (swing.offset - expected).length() < 1e-6,
            "{} vs {expected}",
            swing.offset
        );
        // A state at rest under no drive stays at rest, exactly.
        let mut rest = Swing::default();
        rest.step(&params, DVec2::ZERO, DVec2::ZERO, 0.0, dt);
        assert_eq!(rest, Swing::default());
    }

    /// The body-frame state: a deflection along the heading reads as forward whichever way the
    /// body faces, one to its side as across, and the twist is unchanged.
    #[test]
    fn body_frame_state_follows_the_heading() {
        for heading in [0.0, 0.7, std::f64::consts::PI, -2.0] {
            let forward = DVec2::new(f64::sin(heading), f64::cos(heading));
            let across = DVec2::new(f64::cos(heading), -f64::sin(heading));
            let swing = Swing {
                offset: forward * 0.1 + across * 0.02,
                velocity: across * -0.3,
                twist: 0.25,
                twist_rate: -1.5,
            };
            let state = swing.in_body_frame(heading);
            let want = [0.1, 0.02, 0.0, -0.3, 0.25, -1.5];
            for (got, want) in state.iter().zip(want) {
                assert!((got - want).abs() < 1e-12, "heading {heading}: {state:?}");
            }
        }
    }

    /// The swing turns rows about the waist centre: lengths to the centre are kept, the hem
    /// moves by about the deflection, and the waist ring does not move.
    #[test]
    fn applied_swing_turns_rows_about_the_waist() {
        let (model, shaped, transforms) = rest_state();
        let skirt = Skirt::new(&model, &shaped, 1.0);
        let drape = skirt.carried(&transforms, DAffine3::IDENTITY);
        let params = SwingParams::HISTORY;
        let swing = Swing {
            offset: DVec2::new(0.05, 0.0),
            twist: 0.1,
            ..Default::default()
        };
        let moved = swing.apply(&params, &drape);
        let centre = drape[..AROUND].iter().copied().sum::<DVec3>() / AROUND as f64;
        for (i, (a, b)) in drape.iter().zip(&moved).enumerate() {
            if i < AROUND {
                assert_eq!(a, b);
            }
            assert!(((*a - centre).length() - (*b - centre).length()).abs() < 1e-12);
        }
        let hem_shift = (0..AROUND)
            .map(|k| moved[particle(ROWS - 1, k)] - drape[particle(ROWS - 1, k)])
            .sum::<DVec3>()
            / AROUND as f64;
        // The twist averages out around the ring; the swing moves the hem along +x.
        assert!(hem_shift.x > 0.03 && hem_shift.x < 0.07, "{hem_shift}");
        assert!(hem_shift.z.abs() < 0.01, "{hem_shift}");
    }
}
