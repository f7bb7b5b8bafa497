//! The twin's follower stage: its own errors, repeatable functions of its encoder position and
//! of the direction it last moved in (DESIGN §4, §9).
//!
//! Along its axis: a long-wavelength shape (two sines over the travel, within
//! ±`positioning_um`), the ball screw's periodic term (`periodic_um` at the screw's lead
//! `lead_mm`) and a reversal error (`reversal_um`: the stage stands `reversal_um / 2` behind
//! its encoder in the direction it last moved). Vertically: a straightness within
//! ±`straightness_um` (it reads as roll, 1.38″ per µm), the same in both directions. Every
//! term is zero at encoder 0 moving up, so the follower's home is its reference.
//!
//! What is the instrument's and what the set-up's (issue 26): the shapes above are the stage's
//! own, drawn from the instrument's identity (`instrument_seed`, the same stage on every
//! machine it is set up on); bolted to a machine's bed, the rail also bends with the bed and
//! its feet (`bend_um`: a smooth vertical shape, a tilt, a sag and an S over the travel, drawn
//! for each set-up). A damaged rail adds a kink ([`Kink`]): its vertical turns by an angle at
//! one place, which no smooth bend is.
//!
//! The stage can write its own calibration certificate as a vendor would
//! ([`FollowerModel::certificate`]): its true along-axis error at 10 mm spacing in both
//! directions, with 0.2 µm measurement noise, in the format `follower::Certificate` reads.

use super::Rng;
use crate::units::MM_PER_UM;
use std::f64::consts::PI;

/// The follower stage's own errors (µm and mm, as configured under `[twin.follower]`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FollowerSpec {
    /// Peak long-wavelength positioning error along its axis (µm).
    pub positioning_um: f64,
    /// Peak vertical straightness (µm); it reads as roll (1.38″ per µm) unless mapped.
    pub straightness_um: f64,
    /// Amplitude of the screw-periodic positioning term (µm) and the screw's lead (mm).
    pub periodic_um: f64,
    pub lead_mm: f64,
    /// Reversal error (µm): the difference between the two directions.
    pub reversal_um: f64,
    /// The instrument's identity: its own shapes drawn from this seed, whatever machine it is
    /// set up on (`None`: from the machine's seed, a new stage for each machine).
    pub instrument_seed: Option<u64>,
    /// Peak of the set-up's vertical bend over the travel (µm; drawn from the machine's seed).
    pub bend_um: f64,
    /// The instrument's rail (mm): its own shapes are drawn over this length, whatever axis
    /// it is set up on (`None`: over the axis's travel, a stage made for each axis).
    pub rail_mm: Option<f64>,
    /// Damage: a kink in the rail's vertical.
    pub kink: Option<Kink>,
}

/// A kink in the rail: from `at_mm` on, its vertical turns by `urad` (µrad).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Kink {
    pub at_mm: f64,
    pub urad: f64,
}

impl Default for FollowerSpec {
    fn default() -> Self {
        FollowerSpec {
            positioning_um: 4.0,
            straightness_um: 2.0,
            periodic_um: 1.0,
            lead_mm: 5.0,
            reversal_um: 1.0,
            instrument_seed: None,
            bend_um: 0.0,
            rail_mm: None,
            kink: None,
        }
    }
}

/// The direction the follower last moved in.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Motion {
    #[default]
    Up,
    Down,
}

/// A sine term `amp · sin(2π x / wavelength + phase)` (amp in mm).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Sine {
    amp: f64,
    wavelength: f64,
    phase: f64,
}

impl Sine {
    fn at(&self, x: f64) -> f64 {
        self.amp * (2.0 * PI * x / self.wavelength + self.phase).sin()
    }
}

/// The follower's errors, drawn once from its spec and a seed.
#[derive(Clone, Debug, PartialEq)]
pub struct FollowerModel {
    pub spec: FollowerSpec,
    /// The stage's travel the shapes are drawn over (mm).
    pub travel_mm: f64,
    along: [Sine; 2],
    periodic: Sine,
    vertical: [Sine; 2],
    /// The set-up's bend: coefficients (mm) of t, t² − 1/3 and t³ − 3t/5 over the travel
    /// (t from −1 to 1).
    bend: [f64; 3],
}

/// The shortest wavelength of the long-wavelength shapes (mm): a stage's guides and screw
/// bend over a few hundred mm, whatever the travel.
const LONG_MIN_MM: f64 = 100.0;

/// The stage's reversal error switches once its encoder has gone this far back from its
/// furthest point (mm): a servo's settling back-step smaller than that stays in the stage's
/// play (the tracker judges a turn by the same distance).
pub const TURN_MM: f64 = 0.5e-3;

/// The direction after the encoder moved to `d`, from the direction `now` and the furthest
/// point `anchor` in it (updated).
pub fn motion_after(now: Motion, anchor: &mut f64, d: f64) -> Motion {
    let (further, turned) = match now {
        Motion::Up => (d > *anchor, d < *anchor - TURN_MM),
        Motion::Down => (d < *anchor, d > *anchor + TURN_MM),
    };
    if further || turned {
        *anchor = d;
    }
    match (now, turned) {
        (m, false) => m,
        (Motion::Up, true) => Motion::Down,
        (Motion::Down, true) => Motion::Up,
    }
}

/// The noise (µm, one standard deviation) of the twin's certificate, and its spacing (mm).
pub const CERTIFICATE_NOISE_UM: f64 = 0.2;
pub const CERTIFICATE_STEP_MM: f64 = 10.0;

impl FollowerModel {
    /// Draw the follower's error shapes from `rng` over its rail (`spec.rail_mm`, else
    /// `travel_mm`), for an axis of `travel_mm`.
    pub fn new(spec: FollowerSpec, travel_mm: f64, rng: &mut Rng) -> FollowerModel {
        let len = travel_mm.max(1.0);
        let rail = spec.rail_mm.unwrap_or(len).max(1.0);
        let long = |peak_um: f64, r: &mut Rng| {
            // Two long waves: one of 0.5 to 2 cycles over the travel, a smaller one of 2 to 4,
            // neither shorter than the stage's build allows (LONG_MIN_MM).
            [
                Sine {
                    amp: 0.35 * peak_um * MM_PER_UM,
                    wavelength: (rail / r.uniform(0.5, 2.0)).max(2.0 * LONG_MIN_MM),
                    phase: r.uniform(0.0, 2.0 * PI),
                },
                Sine {
                    amp: 0.15 * peak_um * MM_PER_UM,
                    wavelength: (rail / r.uniform(2.0, 4.0)).max(LONG_MIN_MM),
                    phase: r.uniform(0.0, 2.0 * PI),
                },
            ]
        };
        let along = long(spec.positioning_um, rng);
        let vertical = long(spec.straightness_um, rng);
        let periodic = Sine {
            amp: spec.periodic_um * MM_PER_UM,
            wavelength: spec.lead_mm.max(0.1),
            phase: rng.uniform(0.0, 2.0 * PI),
        };
        FollowerModel {
            spec,
            travel_mm: len,
            along,
            periodic,
            vertical,
            bend: [0.0; 3],
        }
    }

    /// The stage as set up on a machine: its bend within ±`spec.bend_um` drawn from `rng`
    /// (the set-up's own draw).
    pub fn set_up(mut self, rng: &mut Rng) -> FollowerModel {
        let peak = self.spec.bend_um * MM_PER_UM;
        // A tilt, a sag and an S, each up to its share of the peak (|t|, |t² − 1/3| ≤ 2/3,
        // |t³ − 3t/5| ≤ 2/5 over the travel): together within the peak.
        self.bend = [
            rng.uniform(-0.3, 0.3) * peak,
            rng.uniform(-0.75, 0.75) * peak,
            rng.uniform(-0.5, 0.5) * peak,
        ];
        self
    }

    fn bend_at(&self, x: f64) -> f64 {
        let t = 2.0 * x / self.travel_mm - 1.0;
        let b = &self.bend;
        let kink = self
            .spec
            .kink
            .map_or(0.0, |k| k.urad * 1e-6 * (x - k.at_mm).max(0.0));
        b[0] * t + b[1] * (t * t - 1.0 / 3.0) + b[2] * (t * t * t - 0.6 * t) + kink
    }

    fn along_raw(&self, d: f64, dir: Motion) -> f64 {
        let half = self.spec.reversal_um * MM_PER_UM / 2.0;
        let rev = match dir {
            Motion::Up => -half,
            Motion::Down => half,
        };
        self.along.iter().map(|s| s.at(d)).sum::<f64>() + self.periodic.at(d) + rev
    }

    /// Where PSD2 really is along the follower's axis relative to its encoder (mm), at encoder
    /// position `d` after a motion in `dir`.
    pub fn along(&self, d: f64, dir: Motion) -> f64 {
        self.along_raw(d, dir) - self.along_raw(0.0, Motion::Up)
    }

    /// Just the screw-periodic term (mm), relative to encoder 0.
    pub fn periodic(&self, d: f64) -> f64 {
        self.periodic.at(d) - self.periodic.at(0.0)
    }

    /// How far PSD2 is above where it would be on a straight stage (mm), at encoder `d`.
    pub fn vertical(&self, d: f64) -> f64 {
        let v = |x: f64| self.vertical.iter().map(|s| s.at(x)).sum::<f64>() + self.bend_at(x);
        v(d) - v(0.0)
    }

    /// The follower's certificate as a vendor would write it (the format of
    /// `follower::Certificate`): its along-axis error (µm) every 10 mm from −10 mm to 10 mm
    /// past `travel_mm` (the stage's whole stroke, rounded up to the spacing), moving up,
    /// then moving down, each with 0.2 µm of noise drawn from `rng` and stated as its standard
    /// uncertainty.
    pub fn certificate(&self, rng: &mut Rng) -> String {
        let n = ((self.travel_mm + 20.0) / CERTIFICATE_STEP_MM).ceil() as usize;
        let mut out = String::from(
            "# axiscomp twin follower: calibration certificate of the stage's encoder\n\
             # error = actual - indicated position, laser interferometer, 20.0 C\n\
             position_mm,error_um,direction,uncertainty_um\n",
        );
        for (dir, sign) in [(Motion::Up, "+"), (Motion::Down, "-")] {
            for k in 0..=n {
                let d = k as f64 * CERTIFICATE_STEP_MM - 10.0;
                let e = self.along(d, dir) * 1e3 + rng.gauss(CERTIFICATE_NOISE_UM);
                out.push_str(&format!("{d:.3},{e:.3},{sign},{CERTIFICATE_NOISE_UM:.2}\n"));
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn errors_are_repeatable_and_within_their_spec() {
        let spec = FollowerSpec::default();
        let a = FollowerModel::new(spec, 1000.0, &mut Rng::new(5));
        let b = FollowerModel::new(spec, 1000.0, &mut Rng::new(5));
        assert_eq!(a, b);
        assert_eq!(a.along(0.0, Motion::Up), 0.0);
        assert_eq!(a.vertical(0.0), 0.0);
        let mut vmax: f64 = 0.0;
        for k in 0..=1000 {
            let d = k as f64;
            let rev = a.along(d, Motion::Down) - a.along(d, Motion::Up);
            assert!((rev - 1e-3).abs() < 1e-12, "reversal {rev}");
            vmax = vmax.max(a.vertical(d).abs());
            assert!(a.along(d, Motion::Up).abs() <= 2.0 * (4.0 + 1.0) * 1e-3);
        }
        assert!(
            vmax > 0.5e-3 && vmax <= 2.0 * 2.0e-3,
            "vertical peak {vmax}"
        );
        // The periodic term repeats with the screw's lead.
        assert!((a.periodic(12.0) - a.periodic(17.0)).abs() < 1e-12);
    }

    #[test]
    fn an_instrument_s_rail_keeps_its_shape_on_any_axis() {
        let spec = FollowerSpec {
            rail_mm: Some(1000.0),
            ..FollowerSpec::default()
        };
        let bench = FollowerModel::new(spec, 1000.0, &mut Rng::new(8));
        let short = FollowerModel::new(spec, 600.0, &mut Rng::new(8));
        for k in 0..=60 {
            let d = 10.0 * k as f64;
            assert_eq!(short.along(d, Motion::Up), bench.along(d, Motion::Up));
            assert_eq!(short.vertical(d), bench.vertical(d));
        }
        // Without a rail the stage is drawn over the axis: another shape on a shorter one.
        let own = |len| FollowerModel::new(FollowerSpec::default(), len, &mut Rng::new(8));
        let (a, b) = (own(1000.0), own(600.0));
        assert!(
            (0..=60)
                .any(|k| (a.vertical(10.0 * k as f64) - b.vertical(10.0 * k as f64)).abs() > 1e-5)
        );
    }

    #[test]
    fn the_set_up_bends_the_instruments_own_shape_smoothly_and_a_kink_turns_it() {
        let spec = FollowerSpec {
            bend_um: 2.0,
            ..FollowerSpec::default()
        };
        let own = FollowerModel::new(spec, 1000.0, &mut Rng::new(5));
        let a = own.clone().set_up(&mut Rng::new(1));
        let b = own.clone().set_up(&mut Rng::new(2));
        let bend = |m: &FollowerModel, d: f64| m.vertical(d) - own.vertical(d);
        let (mut peak_a, mut differ) = (0.0f64, 0.0f64);
        for k in 0..=100 {
            let d = 10.0 * k as f64;
            // Along the axis the set-up changes nothing; vertically a bend within the peak
            // (relative to encoder 0: twice it at most).
            assert_eq!(a.along(d, Motion::Up), own.along(d, Motion::Up));
            peak_a = peak_a.max(bend(&a, d).abs());
            differ = differ.max((bend(&a, d) - bend(&b, d)).abs());
            // Smooth: its second difference over 10 mm is a few nm (a kink's is its angle
            // times 10 mm: 50 nm for 5 µrad).
            if k > 0 && k < 100 {
                let dd = bend(&a, d - 10.0) - 2.0 * bend(&a, d) + bend(&a, d + 10.0);
                assert!(dd.abs() < 5e-6, "at {d}: {dd}");
            }
        }
        assert!(peak_a > 0.1e-3 && peak_a <= 4.0e-3, "bend {peak_a}");
        assert!(differ > 0.1e-3, "two set-ups bend alike: {differ}");
        let kinked = FollowerModel::new(
            FollowerSpec {
                kink: Some(Kink {
                    at_mm: 400.0,
                    urad: 5.0,
                }),
                ..spec
            },
            1000.0,
            &mut Rng::new(5),
        );
        assert_eq!(kinked.vertical(300.0), own.vertical(300.0));
        let dd =
            |m: &FollowerModel| m.vertical(390.0) - 2.0 * m.vertical(400.0) + m.vertical(410.0);
        assert!((dd(&kinked) - dd(&own) - 5e-5).abs() < 1e-12);
        let d = kinked.vertical(600.0) - own.vertical(600.0);
        assert!((d - 1e-3).abs() < 1e-12, "{d}");
    }

    #[test]
    fn the_stage_turns_only_after_going_back_by_the_turn_distance() {
        let mut anchor = 0.0;
        let mut m = Motion::Up;
        for d in [1.0, 2.0, 2.0 - 0.4e-3, 2.0 - 0.2e-3] {
            m = motion_after(m, &mut anchor, d);
            assert_eq!(m, Motion::Up, "at {d}");
        }
        assert_eq!(anchor, 2.0);
        m = motion_after(m, &mut anchor, 2.0 - 0.6e-3);
        assert_eq!((m, anchor), (Motion::Down, 2.0 - 0.6e-3));
        m = motion_after(m, &mut anchor, 1.5);
        m = motion_after(m, &mut anchor, 1.5 + 0.3e-3);
        assert_eq!((m, anchor), (Motion::Down, 1.5));
    }

    #[test]
    fn the_certificate_is_the_true_map_within_its_noise() {
        let m = FollowerModel::new(FollowerSpec::default(), 200.0, &mut Rng::new(9));
        let text = m.certificate(&mut Rng::new(10));
        let rows: Vec<&str> = text.lines().filter(|l| !l.starts_with('#')).collect();
        assert_eq!(rows[0], "position_mm,error_um,direction,uncertainty_um");
        assert_eq!(rows.len(), 1 + 2 * 23);
        for r in &rows[1..] {
            let f: Vec<&str> = r.split(',').collect();
            let d: f64 = f[0].parse().unwrap();
            let e: f64 = f[1].parse().unwrap();
            let dir = if f[2] == "+" {
                Motion::Up
            } else {
                Motion::Down
            };
            assert!((e - m.along(d, dir) * 1e3).abs() < 5.0 * CERTIFICATE_NOISE_UM);
        }
    }
}
