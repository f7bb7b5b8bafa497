//! The head's turns on its mount found since the zero (knocks, `align::knock` and
//! `align::revisit`), taken out of every frame, with what they leave in each error's variance:
//! the turns' own uncertainty until a return to the zero bounds it, and the moves a turn
//! about a pivot off the nominal one makes besides (read with the knock, or stated by the
//! pivot's uncertainty).

use crate::align::{
    Agreement, Knock, KnockSettings, KnockWatch, Mount, MountGeometry, Revisit, RevisitSettings,
};
use crate::optics::Layout;
use crate::units::Errors6;

/// The head's moves at its knocks beyond what their turns about the mount's nominal pivot
/// explain: read where the knock was found in the frames (`align::Step`), and for the turns
/// found at a return to the zero, which read no step, what the pivot's uncertainty leaves.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Shifts {
    /// dx, dy, dz (mm) read beyond the turns, taken out of every frame with them.
    pub mm: [f64; 3],
    /// Their variance (mm²).
    pub var_mm2: [f64; 3],
    /// The yaw and pitch (rad) of the turns whose move was not read: since the zero, and since
    /// the last return to the zero that agreed (which reads dx and dz, not dy).
    pub unread_rad: [f64; 2],
    pub unread_since_agreed_rad: [f64; 2],
}

impl Shifts {
    /// Every turn's move unread: a row kept before the moves were recorded.
    pub(super) fn unread(turn_rad: [f64; 2], pending: bool) -> Shifts {
        Shifts {
            unread_rad: turn_rad,
            unread_since_agreed_rad: if pending { turn_rad } else { [0.0; 2] },
            ..Shifts::default()
        }
    }

    pub(super) fn numbers(&self) -> impl Iterator<Item = &f64> {
        self.mm
            .iter()
            .chain(&self.var_mm2)
            .chain(&self.unread_rad)
            .chain(&self.unread_since_agreed_rad)
    }
}

/// How well a turn found as a step in pitch and yaw is known beyond its fit's noise (rad): the
/// lab's knocks (seeds 4, 9, 17 at rest; 5, 12 in moves) are found within 0.3 µrad of the turn
/// made while their fits state 0.1 µrad, the follower's place on PSD2 at the knock moving the
/// estimate by as much. Until the next return to the zero that agrees (`Turned::bound`).
pub(super) const TURN_MODEL_SD_RAD: f64 = 0.25e-6;

/// How far the mount's true pivot may lie from its nominal place, as a standard uncertainty
/// in each axis (mm): a screw mount's base puts it where its drawing says within ±20 mm
/// (rectangular). A turn θ about a pivot Δ off moves the head by θ·Δ: 10 µrad of yaw, 0.2 µm
/// in dy for a pivot 20 mm off across the axis, which no return to the zero reads.
pub(super) const PIVOT_SD_MM: f64 = PIVOT_TOLERANCE_MM / 1.732_050_807_568_877_2;
const PIVOT_TOLERANCE_MM: f64 = 20.0;

/// A knock's steps in dx, dy and dz are taken as its move only when each is read to this
/// (mm, standard deviation; at rest the reference head reads them to about 0.03 µm) and lies
/// within what a turn about a pivot inside its tolerance can move (half as much again, and 4
/// sd). Else something else moved in the frames the step was fitted on: a storm's knock in a
/// dwell 0.8 s before the follower's drive faulted read dy stepping by -10.8 ± 1.0 µm with a
/// 3.7 µrad turn, and taken out it put every later capture 10.4 µm off the truth. Such a
/// turn's move counts as unread.
const STEP_SD_MAX_MM: f64 = 0.1e-3;
const STEP_REACH: f64 = 1.5;

/// The head's turns on its mount found since the zero (knocks), taken out of every frame.
#[derive(Clone, Debug)]
pub(super) struct Turned {
    pub(super) watch: KnockWatch,
    /// Each return to the zero's place, checked for a turn since the last one.
    pub(super) revisit: Revisit,
    /// The sum of the turns found.
    pub(super) turn: Mount,
    /// The variance of the yaw and pitch of the turns found since the last return that agreed
    /// (since the zero before one) (rad²).
    pub(super) var: [f64; 2],
    /// What the last return that agreed read of the turns found before it.
    pub(super) seen: Option<Agreement>,
    /// A knock found and not yet taken by the caller.
    pub(super) found: Option<Knock>,
    /// A return agreed while turns found since the last one were known only by their own
    /// variance, not yet taken by the caller (`Measure::take_bounded`).
    pub(super) bounded: Option<Agreement>,
    /// What the knocks moved the head by beyond their turns.
    pub(super) shifts: Shifts,
}

impl Turned {
    pub(super) fn new() -> Self {
        Turned {
            watch: KnockWatch::new(KnockSettings::default()),
            revisit: Revisit::new(RevisitSettings::default()),
            turn: Mount::default(),
            var: [0.0; 2],
            seen: None,
            found: None,
            bounded: None,
            shifts: Shifts::default(),
        }
    }

    /// No turn, no zero to check returns against (the side the carriage is on is kept).
    pub(super) fn reset(&mut self) {
        let mut revisit = std::mem::replace(&mut self.revisit, Revisit::new(Default::default()));
        revisit.forget();
        *self = Turned {
            revisit,
            ..Turned::new()
        };
    }

    pub(super) fn head_pose(m: Mount, layout: &Layout, travel: f64, e: &Errors6) -> Errors6 {
        m.head_pose(
            MountGeometry::default().pivot(),
            layout.c,
            layout.travel_axis,
            travel,
            e,
        )
    }

    /// `e` as the head read it before its turns, at `travel`.
    pub(super) fn undo(&self, layout: &Layout, travel: f64, e: Errors6) -> Errors6 {
        if self.turn == Mount::default() && self.shifts.mm == [0.0; 3] {
            return e;
        }
        let back = Mount {
            yaw: -self.turn.yaw,
            pitch: -self.turn.pitch,
            ..Mount::default()
        };
        let mut e = Self::head_pose(back, layout, travel, &e);
        e.dx -= self.shifts.mm[0];
        e.dy -= self.shifts.mm[1];
        e.dz -= self.shifts.mm[2];
        e
    }

    /// What a turn of `yaw` and `pitch` does to each error at `travel`.
    pub(super) fn effect(layout: &Layout, travel: f64, yaw: f64, pitch: f64) -> [f64; 6] {
        let m = Mount {
            yaw,
            pitch,
            ..Mount::default()
        };
        Self::head_pose(m, layout, travel, &Errors6::ZERO).to_array()
    }

    /// The variance the turns' uncertainty adds to each error at `travel`: the turns found
    /// since the last return that agreed by their own variance; those before it by what that
    /// return read (`Turned::bound`), the zero being at `zero_travel`.
    pub(super) fn var_at(&self, layout: &Layout, travel: f64, zero_travel: f64) -> [f64; 6] {
        let mut v = [0.0; 6];
        if self.var != [0.0; 2] {
            let y = Self::effect(layout, travel, self.var[0].sqrt(), 0.0);
            let p = Self::effect(layout, travel, 0.0, self.var[1].sqrt());
            v = std::array::from_fn(|k| y[k] * y[k] + p[k] * p[k]);
        }
        if let Some(a) = &self.seen {
            // pitch, yaw, dx, dz as read: each bounded by its square plus its variance.
            let b: [f64; 4] = std::array::from_fn(|k| a.mean[k].hypot(a.sd[k]));
            // The straightness off at the zero, and the turn's part that grows from there.
            let unit = 1e-6;
            let (y, y0) = (
                Self::effect(layout, travel, unit, 0.0),
                Self::effect(layout, zero_travel, unit, 0.0),
            );
            let (p, p0) = (
                Self::effect(layout, travel, 0.0, unit),
                Self::effect(layout, zero_travel, 0.0, unit),
            );
            v[0] += (b[2] + b[1] * ((y[0] - y0[0]) / unit).abs()).powi(2);
            v[2] += (b[3] + b[0] * ((p[2] - p0[2]) / unit).abs()).powi(2);
            v[3] += b[0] * b[0];
            v[5] += b[1] * b[1];
        }
        // The moves read at the knocks, and what the pivot's uncertainty leaves of the turns
        // whose move was not read: in dy always (a return reads no dy), across the beam until
        // a return reads dx and dz (yaw about z moves x by the pivot's y, y by its x; pitch
        // about x moves z by its y, y by its z).
        let m = &self.shifts;
        let (yaw, pitch) = (m.unread_rad[0], m.unread_rad[1]);
        let (yaw_since, pitch_since) = (m.unread_since_agreed_rad[0], m.unread_since_agreed_rad[1]);
        let p2 = PIVOT_SD_MM * PIVOT_SD_MM;
        v[0] += m.var_mm2[0] + yaw_since * yaw_since * p2;
        v[1] += m.var_mm2[1] + (yaw * yaw + pitch * pitch) * p2;
        v[2] += m.var_mm2[2] + pitch_since * pitch_since * p2;
        v
    }

    /// A return to the zero agreed: where the turns found so far would leave the head reading
    /// nothing against the zero (within the axis' own repeatability, which only adds to what
    /// is read), it reads `a.mean` ± `a.sd`. Each reading's square plus its variance (its
    /// expectation: the error's variance and the noise's twice) bounds the turns' error from
    /// then on, in place of their own variance: in pitch and yaw as read, in dx and dz as
    /// read at the zero plus the turn's part growing with the distance from it (a turn found
    /// about a pivot a little off the head's true one leaves a straightness offset that the
    /// angles do not show). The turn itself is left as found, so that neither the noise of
    /// one stay nor the axis' own return is taken for a turn. Refined as the stay's frames
    /// come in. Without a turn found since the zero, there is nothing to bound.
    pub(super) fn bound(&mut self, a: Agreement) {
        if self.var == [0.0; 2] && self.seen.is_none() {
            return;
        }
        if self.var != [0.0; 2] {
            self.bounded = Some(a);
        }
        self.var = [0.0; 2];
        self.seen = Some(a);
        self.shifts.unread_since_agreed_rad = [0.0; 2];
    }

    /// Whether turns found since the last return that agreed are known only by their own
    /// variance (a later return bounds them).
    pub(super) fn pending(&self) -> bool {
        self.var != [0.0; 2]
    }

    /// A knock found with the carriage at `travel`: its turn taken out of every frame from now
    /// on, and the move it read beyond what the turn about the nominal pivot explains there.
    pub(super) fn add(&mut self, k: Knock, layout: &Layout, travel: f64) {
        let explained = Self::effect(layout, travel, k.turn.yaw, k.turn.pitch);
        let reach = (k.turn.yaw.abs() + k.turn.pitch.abs()) * PIVOT_TOLERANCE_MM * STEP_REACH;
        let read = k.step.filter(|step| {
            let ok = (0..3).all(|i| {
                let sd = step.sd_mm[i];
                sd <= STEP_SD_MAX_MM && (step.mm[i] - explained[i]).abs() <= reach + 4.0 * sd
            });
            if !ok {
                tracing::info!(
                    dx_um = step.mm[0] * 1e3,
                    dy_um = step.mm[1] * 1e3,
                    dz_um = step.mm[2] * 1e3,
                    sd_um = step.sd_mm.iter().fold(0.0f64, |a, b| a.max(*b)) * 1e3,
                    "a knock's move not read: its steps are not what a turn about the mount's \
                     pivot makes; the pivot's uncertainty is stated instead"
                );
            }
            ok
        });
        match read {
            Some(step) => {
                let beyond: [f64; 3] = std::array::from_fn(|i| step.mm[i] - explained[i]);
                let m = &mut self.shifts;
                m.mm = std::array::from_fn(|i| m.mm[i] + beyond[i]);
                m.var_mm2 = std::array::from_fn(|i| m.var_mm2[i] + step.sd_mm[i].powi(2));
                tracing::debug!(
                    dx_um = beyond[0] * 1e3,
                    dy_um = beyond[1] * 1e3,
                    dz_um = beyond[2] * 1e3,
                    "a knock's move beyond its turn about the nominal pivot"
                );
            }
            None => {
                let m = &mut self.shifts;
                for a in [&mut m.unread_rad, &mut m.unread_since_agreed_rad] {
                    a[0] += k.turn.yaw;
                    a[1] += k.turn.pitch;
                }
            }
        }
        self.turn = self.turn.plus(k.turn);
        // The fit's sd is its noise alone; the turn's reading of the head's pose is known to
        // TURN_MODEL_SD_RAD beyond it.
        self.var[0] += k.sd_rad[0].powi(2) + TURN_MODEL_SD_RAD.powi(2);
        self.var[1] += k.sd_rad[1].powi(2) + TURN_MODEL_SD_RAD.powi(2);
        self.found = Some(k);
    }
}
