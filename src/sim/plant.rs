//! The twin's physical state, shared by its parts: the carriage on the measured axis, the
//! follower stage carrying PSD2 (with its own positioning and vertical straightness errors),
//! the head (installation errors, noise, laser pointing drift), how the head is mounted on the
//! machine (a misalignment drawn at random, adjusted by turning its screws) and beam blockers.
//!
//! The twin's I/O module samples it (`sample`), the twin's drive sets the follower's encoder
//! position (`set_follower_encoder`), the motion interface moves the carriage (`move_carriage`),
//! and tests read the truth (`truth`).

use super::axis::{AxisProfile, AxisSpec, Carriage, Direction};
use super::{InstallSpec, Rng, SimError, TwinHead};
use crate::align::{Mount, MountGeometry, Screw};
use crate::optics::geometry::{V3, rot_zyx};
use crate::optics::layout::Kind;
use crate::optics::{Layout, Pose, Spot};
use crate::units::Errors6;
use std::sync::Mutex;
use std::time::Instant;

pub use super::follower::{FollowerModel, FollowerSpec, Motion};

/// How far from aligned the head is mounted (uniform within ±): yaw and pitch of the head's
/// base to the axis, and its offsets across the travel.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct MountSpec {
    pub angle_deg: f64,
    pub offset_mm: f64,
}

impl MountSpec {
    /// A technician's first mounting, by eye and a rule: up to 0.3° and 2 mm.
    pub fn by_eye() -> MountSpec {
        MountSpec {
            angle_deg: 0.3,
            offset_mm: 2.0,
        }
    }
}

/// How much a real mount's screws differ from their nominal travel per turn (±), and how far
/// its pivot is from the nominal one (mm, ±).
const SCREW_ERROR: f64 = 0.05;
const PIVOT_ERROR_MM: f64 = 20.0;

/// The ruled alignment target in front of each PSD: its half-size and the resolution a
/// technician reads it to (mm).
pub const TARGET_HALF_MM: f64 = 20.0;
pub const TARGET_RESOLUTION_MM: f64 = 0.5;

/// Something that happens to the plant at a set instant (for tests on the virtual clock).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PlantEvent {
    /// Block (or clear) the beams to the PSDs flagged.
    Block([bool; 3]),
    /// The head is knocked on its mount (rad, mm added).
    Knock(Mount),
    /// The follower's encoder slips (after a following error, a crash of the stage): from
    /// now on the stage sits this much (mm) beyond what its encoder reads.
    EncoderSlip(f64),
}

/// Everything the plant is built from.
#[derive(Clone, Debug, PartialEq)]
pub struct PlantSpec {
    pub seed: u64,
    pub axis: AxisSpec,
    pub install: InstallSpec,
    /// PSD noise per axis (mm).
    pub noise_mm: f64,
    /// Laser pointing drift: random-walk rate (rad per √s) of the beam's two tilt angles.
    pub beam_drift_rad_per_sqrt_s: f64,
    pub follower: FollowerSpec,
    /// The head's mounting error (none by default: aligned exactly).
    pub mount: MountSpec,
    /// SUM signal with the beam on a PSD (V), and with it blocked.
    pub sum_on_v: f64,
    pub sum_off_v: f64,
    /// Carriage feed (mm/s) and acceleration (mm/s²).
    pub feed: f64,
    pub accel: f64,
    /// The twin's electronic level on the carriage (a simulated instrument, read on the
    /// control socket's `level` command): the standard deviation of one reading (rad).
    pub level_sd_rad: f64,
}

impl Default for PlantSpec {
    fn default() -> Self {
        PlantSpec {
            seed: 1,
            axis: AxisSpec::default(),
            install: InstallSpec::default(),
            noise_mm: 1e-3,
            beam_drift_rad_per_sqrt_s: 0.0,
            follower: FollowerSpec::default(),
            mount: MountSpec::default(),
            sum_on_v: 5.0,
            sum_off_v: 0.02,
            feed: 50.0,
            accel: 500.0,
            level_sd_rad: 1e-6,
        }
    }
}

/// What the PSDs deliver at one instant: spot (mm) and SUM (V) per PSD.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PsdSample {
    pub spots: [Option<Spot>; 3],
    pub sums: [f64; 3],
}

/// The twin's truth at one instant.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Truth {
    /// Nominal carriage position D (mm) and whether it is moving.
    pub travel: f64,
    pub moving: bool,
    /// The axis' true six errors at D (internal units).
    pub errors: Errors6,
    /// The follower's encoder position, and where PSD2 really is along and across its axis (mm).
    pub follower_encoder: f64,
    pub follower_true: f64,
    pub follower_vertical: f64,
    /// The direction the follower last moved in (its reversal error depends on it).
    pub follower_motion: Motion,
    /// How the head is mounted (rad, mm).
    pub mount: Mount,
}

/// A correction profile along the travel (mm), linear between points, held beyond the ends;
/// separate values for the − direction when given.
#[derive(Clone, Debug, PartialEq)]
pub struct Profile {
    pub positions_mm: Vec<f64>,
    pub up_mm: Vec<f64>,
    pub down_mm: Option<Vec<f64>>,
}

impl Profile {
    /// The correction at `d` approached in `dir`.
    pub fn at(&self, d: f64, dir: Direction) -> f64 {
        let v = match (dir, &self.down_mm) {
            (Direction::Down, Some(down)) => down,
            _ => &self.up_mm,
        };
        crate::util::interpolate(&self.positions_mm, v, d)
    }
}

/// Compensation the twin's PLC applies to the axis: corrections added to the carriage's
/// position along the travel (head y) and across it (head x, head z), as a controller adds
/// its table values to the commanded position.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Compensation {
    pub dy: Option<Profile>,
    pub dx: Option<Profile>,
    pub dz: Option<Profile>,
}

struct State {
    carriage: Carriage,
    compensation: Compensation,
    follower_encoder: f64,
    /// How far the stage sits beyond its encoder's reading (mm): slips added up.
    encoder_slip: f64,
    follower_motion: Motion,
    /// The furthest encoder position in the current direction (the turning point).
    follower_anchor: f64,
    blocked: [bool; 3],
    mount: Mount,
    /// Events still to happen, in time order.
    scheduled: Vec<(Instant, PlantEvent)>,
    rng: Rng,
    /// Beam tilt angles (rad) about the laser's u and v.
    drift: [f64; 2],
    drift_at: Instant,
    /// The true layout with the current beam drift applied.
    layout: Layout,
    /// The carriage's last rests, oldest first (at most `RESTS_KEPT`).
    rests: std::collections::VecDeque<Rest>,
}

/// The carriage stood at `mm` (nominal) from `from` to `to`, its last move in `direction`:
/// what a capture taken then was taken at, independent of the service's labels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Rest {
    pub from: Instant,
    pub to: Instant,
    pub mm: f64,
    pub direction: Direction,
}

impl State {
    /// The rest under way at `now` (since the last move ended), if the carriage stands.
    fn rest_until(&self, now: Instant) -> Option<Rest> {
        let end = self.carriage.end();
        (now > end).then(|| Rest {
            from: end,
            to: now,
            mm: self.carriage.target(),
            direction: self.carriage.direction(),
        })
    }
}

/// Rests kept for `Plant::rests`: two whole runs of 110 captures with their moves between.
const RESTS_KEPT: usize = 2048;

/// The twin's plant.
pub struct Plant {
    pub spec: PlantSpec,
    pub head: TwinHead,
    pub axis: AxisProfile,
    /// The follower stage's own errors (`sim::follower`).
    pub follower: FollowerModel,
    /// The real mount's screws and pivot (the nominal ones with their errors).
    pub mount_geometry: MountGeometry,
    laser: Option<usize>,
    t0: Instant,
    state: Mutex<State>,
    /// The calibration hexapod the moving module may sit on (`sim::hexapod_servers`): its
    /// pose adds to the axis' errors. At its home pose it changes nothing.
    pub hexapod: std::sync::Arc<super::hexapod_servers::HexapodMount>,
}

impl Plant {
    /// Build the plant from `spec`, at rest at D = 0 with the follower at 0.
    pub fn new(nominal: &Layout, spec: &PlantSpec, now: Instant) -> Result<Self, SimError> {
        let root = Rng::new(spec.seed);
        let head = Plant::draw_head(nominal, spec)?;
        let axis = AxisProfile::random(&spec.axis, &mut root.fork(12));
        // The stage's own shapes are the instrument's; its bend is this set-up's.
        let mut own = match spec.follower.instrument_seed {
            Some(s) => Rng::new(s).fork(13),
            None => root.fork(13),
        };
        let follower = FollowerModel::new(spec.follower, spec.axis.length_mm, &mut own)
            .set_up(&mut root.fork(19));
        let mut r = root.fork(15);
        let (ma, mo) = (spec.mount.angle_deg.to_radians(), spec.mount.offset_mm);
        let mount = Mount {
            yaw: r.uniform(-ma, ma),
            pitch: r.uniform(-ma, ma),
            x: r.uniform(-mo, mo),
            z: r.uniform(-mo, mo),
        };
        let nominal_mount = MountGeometry::default();
        let mount_geometry = MountGeometry {
            pivot_mm: std::array::from_fn(|i| {
                nominal_mount.pivot_mm[i] + r.uniform(-PIVOT_ERROR_MM, PIVOT_ERROR_MM)
            }),
            per_turn: std::array::from_fn(|i| {
                nominal_mount.per_turn[i] * (1.0 + r.uniform(-SCREW_ERROR, SCREW_ERROR))
            }),
        };
        let laser = head
            .truth
            .elements
            .iter()
            .position(|e| e.kind == Kind::Laser);
        Ok(Plant {
            state: Mutex::new(State {
                carriage: Carriage::new(0.0, spec.feed, spec.accel, now),
                compensation: Compensation::default(),
                follower_encoder: 0.0,
                encoder_slip: 0.0,
                follower_motion: Motion::Up,
                follower_anchor: 0.0,
                blocked: [false; 3],
                mount,
                scheduled: Vec::new(),
                rng: root.fork(14),
                drift: [0.0; 2],
                drift_at: now,
                layout: head.truth.clone(),
                rests: std::collections::VecDeque::new(),
            }),
            spec: spec.clone(),
            head,
            axis,
            follower,
            mount_geometry,
            laser,
            t0: now,
            hexapod: Default::default(),
        })
    }

    /// The head a plant built from `spec` carries (to calibrate it before the plant exists).
    pub fn draw_head(nominal: &Layout, spec: &PlantSpec) -> Result<TwinHead, SimError> {
        let root = Rng::new(spec.seed);
        TwinHead::random(nominal, &spec.install, spec.noise_mm, &mut root.fork(11))
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        // A panic while holding the lock leaves consistent plain data: keep going.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The follower stage's own errors (mm) at encoder position `d` after a motion in `dir`:
    /// along its axis, vertical.
    pub fn follower_errors(&self, d: f64, dir: Motion) -> (f64, f64) {
        (self.follower.along(d, dir), self.follower.vertical(d))
    }

    /// Command the carriage to nominal position `target` (mm).
    pub fn move_carriage(&self, target: f64, now: Instant) {
        let mut s = self.lock();
        if let Some(rest) = s.rest_until(now) {
            if s.rests.len() == RESTS_KEPT {
                s.rests.pop_front();
            }
            s.rests.push_back(rest);
        }
        s.carriage.move_to(target, now);
    }

    /// The carriage's last rests up to `now`, oldest first; the one under way, if any, ends
    /// at `now`.
    pub fn rests(&self, now: Instant) -> Vec<Rest> {
        let s = self.lock();
        s.rests.iter().copied().chain(s.rest_until(now)).collect()
    }

    /// Apply (or remove) the compensation the PLC accepted.
    pub fn set_compensation(&self, c: Compensation) {
        self.lock().compensation = c;
    }

    /// The compensation in effect.
    pub fn compensation(&self) -> Compensation {
        self.lock().compensation.clone()
    }

    /// Set the carriage's feed (mm/s) for the following moves (the CNC's programmed feed).
    pub fn set_feed(&self, feed_mm_s: f64) {
        if feed_mm_s.is_finite() && feed_mm_s > 0.0 {
            self.lock().carriage.feed = feed_mm_s;
        }
    }

    /// Nominal carriage position and whether it is moving.
    pub fn carriage(&self, now: Instant) -> (f64, bool) {
        let s = self.lock();
        (s.carriage.position(now), s.carriage.is_moving(now))
    }

    /// When the current carriage move ends.
    pub fn carriage_move_end(&self) -> Instant {
        self.lock().carriage.end()
    }

    /// Set the follower's encoder position (mm), as its drive moves it.
    pub fn set_follower_encoder(&self, d: f64) {
        let mut guard = self.lock();
        let s = &mut *guard;
        s.follower_motion =
            super::follower::motion_after(s.follower_motion, &mut s.follower_anchor, d);
        s.follower_encoder = d;
    }

    /// The follower's encoder position (mm).
    pub fn follower_encoder(&self) -> f64 {
        self.lock().follower_encoder
    }

    /// The follower's encoder slips by `mm` now ([`PlantEvent::EncoderSlip`]).
    pub fn slip_encoder(&self, mm: f64) {
        self.lock().encoder_slip += mm;
    }

    /// Block or unblock the beam to one PSD (0..3).
    pub fn set_blocked(&self, psd: usize, blocked: bool) {
        if let Some(b) = self.lock().blocked.get_mut(psd) {
            *b = blocked;
        }
    }

    /// Make `event` happen at `at` (it takes effect at the first sample from then on).
    pub fn schedule(&self, at: Instant, event: PlantEvent) {
        let mut s = self.lock();
        s.scheduled.push((at, event));
        s.scheduled.sort_by_key(|(t, _)| *t);
    }

    fn apply_due(s: &mut State, now: Instant) {
        while s.scheduled.first().is_some_and(|(t, _)| *t <= now) {
            let (_, e) = s.scheduled.remove(0);
            match e {
                PlantEvent::Block(b) => s.blocked = b,
                PlantEvent::Knock(m) => s.mount = s.mount.plus(m),
                PlantEvent::EncoderSlip(mm) => s.encoder_slip += mm,
            }
        }
    }

    /// Turn one of the mount's screws by `turns` (clockwise positive), as a technician does.
    pub fn turn_screw(&self, screw: Screw, turns: f64) {
        if turns.is_finite() {
            let amount = self.mount_geometry.amount(screw, turns);
            let mut s = self.lock();
            s.mount = s.mount.adjusted(screw, amount);
        }
    }

    /// Knock the head on its mount (rad, mm added).
    pub fn knock(&self, by: Mount) {
        let mut s = self.lock();
        s.mount = s.mount.plus(by);
    }

    /// How the head is mounted now.
    pub fn mount(&self) -> Mount {
        self.lock().mount
    }

    /// What the alignment target in front of each PSD shows at `now`: the spot (mm, to the
    /// target's resolution) when the beam reaches the PSD's plane within the target, whether
    /// or not it is on the PSD's active area.
    pub fn target_readings(&self, now: Instant) -> [Option<Spot>; 3] {
        let s = self.lock();
        let t = self.truth_locked(&s, now);
        let layout = &s.layout;
        let r = layout.forward(&self.head_pose(&s, &t));
        let round = |v: f64| (v / TARGET_RESOLUTION_MM).round() * TARGET_RESOLUTION_MM;
        std::array::from_fn(|k| {
            if s.blocked[k] {
                return None;
            }
            let on_plane = match r.psd[k] {
                Ok(spot) => Some(spot),
                Err(inv) => match inv.kind {
                    crate::optics::trace::InvalidKind::OffActiveArea { x, y } => {
                        Some(Spot { x, y })
                    }
                    _ => None,
                },
            }?;
            (on_plane.x.abs() <= TARGET_HALF_MM && on_plane.y.abs() <= TARGET_HALF_MM).then(|| {
                Spot {
                    x: round(on_plane.x),
                    y: round(on_plane.y),
                }
            })
        })
    }

    /// The pose the head sees: the axis' errors through the mount, PSD2 where it really is.
    fn head_pose(&self, s: &State, t: &Truth) -> Pose {
        let l = &self.head.truth;
        let e = s.mount.head_pose(
            self.mount_geometry.pivot(),
            l.c,
            l.travel_axis,
            t.travel,
            &t.errors,
        );
        Pose::new(e, t.travel, t.follower_true)
    }

    /// The least-squares slopes (along the head's x and z, per mm of travel) of the
    /// straightness the head sees over `span` with its mount as it is at `now`, without noise:
    /// which way the axis runs against the beam (the line a squareness is measured from).
    pub fn true_slopes(&self, span: (f64, f64), now: Instant) -> [f64; 2] {
        let s = self.lock();
        let l = &self.head.truth;
        let travels: Vec<f64> = (0..=100)
            .map(|i| span.0 + (span.1 - span.0) * i as f64 / 100.0)
            .collect();
        let (mut x, mut z) = (Vec::new(), Vec::new());
        for &p in &travels {
            let e = self.errors_locked(&s, p, Direction::Up, now);
            let seen = s
                .mount
                .head_pose(self.mount_geometry.pivot(), l.c, l.travel_axis, p, &e);
            x.push(seen.dx);
            z.push(seen.dz);
        }
        let slope = |v: &[f64]| {
            crate::evaluate::iso230_1::fit_line(
                &travels,
                v,
                crate::evaluate::ReferenceLine::LeastSquares,
            )
            .map_or(f64::NAN, |f| f.slope)
        };
        [slope(&x), slope(&z)]
    }

    /// The truth at `now`.
    pub fn truth(&self, now: Instant) -> Truth {
        let s = self.lock();
        self.truth_locked(&s, now)
    }

    /// The axis' true errors (the compensation in force and the hexapod's pose included) at
    /// `travel` approached in `dir`, at `now`, wherever the carriage is: what a capture taken
    /// at rest there is judged by.
    pub fn errors_at(&self, travel: f64, dir: Direction, now: Instant) -> Errors6 {
        let s = self.lock();
        self.errors_locked(&s, travel, dir, now)
    }

    fn errors_locked(&self, s: &State, travel: f64, dir: Direction, now: Instant) -> Errors6 {
        let hours = now.saturating_duration_since(self.t0).as_secs_f64() / 3600.0;
        let mut errors = self.axis.errors(travel, dir, hours);
        let c = &s.compensation;
        if let Some(p) = &c.dy {
            errors.dy += p.at(travel, dir);
        }
        if let Some(p) = &c.dx {
            errors.dx += p.at(travel, dir);
        }
        if let Some(p) = &c.dz {
            errors.dz += p.at(travel, dir);
        }
        self.hexapod.apply(&mut errors, now);
        errors
    }

    fn truth_locked(&self, s: &State, now: Instant) -> Truth {
        let travel = s.carriage.position(now);
        let dir: Direction = s.carriage.direction();
        let (fu, fv) = self.follower_errors(s.follower_encoder, s.follower_motion);
        let errors = self.errors_locked(s, travel, dir, now);
        Truth {
            travel,
            moving: s.carriage.is_moving(now),
            errors,
            follower_encoder: s.follower_encoder,
            follower_true: s.follower_encoder + fu + s.encoder_slip,
            follower_vertical: fv,
            follower_motion: s.follower_motion,
            mount: s.mount,
        }
    }

    fn update_drift(&self, s: &mut State, now: Instant) {
        let rate = self.spec.beam_drift_rad_per_sqrt_s;
        let dt = now.saturating_duration_since(s.drift_at).as_secs_f64();
        if rate <= 0.0 || dt < 0.05 {
            return;
        }
        let step = rate * dt.sqrt();
        s.drift[0] += s.rng.gauss(step);
        s.drift[1] += s.rng.gauss(step);
        s.drift_at = now;
        if let Some(i) = self.laser {
            let base = self.head.truth.elements[i].frame;
            let r = rot_zyx(s.drift[0], s.drift[1], 0.0);
            s.layout.elements[i].frame = base.perturbed(V3::zeros(), &r);
        }
    }

    /// What the three PSDs deliver at `now`, with noise.
    pub fn sample(&self, now: Instant) -> PsdSample {
        let mut s = self.lock();
        Plant::apply_due(&mut s, now);
        self.update_drift(&mut s, now);
        let t = self.truth_locked(&s, now);
        let r = s.layout.forward(&self.head_pose(&s, &t));
        let mut spots = [None; 3];
        let mut sums = [self.spec.sum_off_v; 3];
        for k in 0..3 {
            if s.blocked[k] {
                continue;
            }
            if let Ok(mut spot) = r.psd[k] {
                if k == 1 {
                    // PSD2 sits higher by the follower's straightness: the spot reads lower.
                    spot.y -= t.follower_vertical;
                }
                let noise = self.head.noise_mm;
                spot.x += s.rng.gauss(noise);
                spot.y += s.rng.gauss(noise);
                spots[k] = Some(spot);
                sums[k] = self.spec.sum_on_v * (1.0 + s.rng.gauss(0.002));
            }
        }
        PsdSample { spots, sums }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn compensation_moves_the_axis() {
        let t0 = crate::util::clock::now();
        let plant = Plant::new(&Layout::reference(), &PlantSpec::default(), t0).unwrap();
        plant.move_carriage(500.0, t0);
        let t = t0 + Duration::from_secs(30);
        let before = plant.truth(t).errors;
        plant.set_compensation(Compensation {
            dy: Some(Profile {
                positions_mm: vec![0.0, 1000.0],
                up_mm: vec![0.0, -0.02],
                down_mm: None,
            }),
            ..Compensation::default()
        });
        let after = plant.truth(t).errors;
        assert!((after.dy - (before.dy - 0.01)).abs() < 1e-12);
        assert_eq!(after.dx, before.dx);
    }

    /// Each rest is where the carriage stood between two moves, with the direction of the
    /// move that ended there; the one under way ends now.
    #[test]
    fn the_carriage_rests_are_kept_with_their_approach() {
        let t0 = crate::util::clock::now();
        let plant = Plant::new(&Layout::reference(), &PlantSpec::default(), t0).unwrap();
        let s = Duration::from_secs;
        plant.move_carriage(100.0, t0 + s(1));
        let arrived = plant.carriage_move_end();
        plant.move_carriage(40.0, arrived + s(2));
        let back = plant.carriage_move_end();
        let rests = plant.rests(back + s(3));
        let seen: Vec<(f64, Direction, Duration)> = rests
            .iter()
            .map(|r| (r.mm, r.direction, r.to - r.from))
            .collect();
        assert_eq!(
            seen,
            vec![
                (0.0, Direction::Up, s(1)),
                (100.0, Direction::Up, s(2)),
                (40.0, Direction::Down, s(3)),
            ]
        );
        assert_eq!(rests[1].from, arrived);
        // Moving: no rest under way.
        assert_eq!(plant.rests(back - s(1)).len(), 2);
    }

    #[test]
    fn sample_follows_carriage_and_follower() {
        let t0 = crate::util::clock::now();
        let spec = PlantSpec {
            noise_mm: 0.0,
            install: InstallSpec {
                offset_mm: 0.0,
                tilt_deg: 0.0,
                gain_error: 0.0,
            },
            ..PlantSpec::default()
        };
        let plant = Plant::new(&Layout::reference(), &spec, t0).unwrap();
        plant.move_carriage(1.0, t0);
        let later = t0 + Duration::from_secs(2);
        let truth = plant.truth(later);
        assert_eq!(truth.travel, 1.0);
        let s = plant.sample(later);
        let x2 = s.spots[1].unwrap().x;
        // X2 = dx + dy − 340·ez + (D − d) with d = 0 (encoder at 0, follower error 0 there).
        let e = truth.errors;
        let want = e.dx + e.dy - 340.0 * e.ez + 1.0;
        assert!((x2 - want).abs() < 1e-6, "{x2} vs {want}");
        plant.set_follower_encoder(1.0);
        let (fu, fv) = plant.follower_errors(1.0, Motion::Up);
        let s = plant.sample(later);
        assert!((s.spots[1].unwrap().x - (want - 1.0 - fu)).abs() < 1e-6);
        let y2_nominal = 150.0 * (e.ey - e.ex);
        assert!((s.spots[1].unwrap().y - (y2_nominal - fv)).abs() < 1e-6);
        plant.set_blocked(2, true);
        let s = plant.sample(later);
        assert!(s.spots[2].is_none() && s.sums[2] < 0.1 && s.sums[0] > 4.0);
    }
}
