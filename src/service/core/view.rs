//! The core's view of the service: the `Snapshot` the console and `axiscomp status` show, built
//! at each tick from the pipeline, the links and the procedures (each fills its own part).

use super::Core;
use crate::canopen::{DriveStatus, PowerState};
use crate::modbus::{Exception, LinkState};
use crate::service::api::snapshot::{
    FollowerView, LinkView, LinksView, LiveView, PsdView, Snapshot, TrackingView,
};
use crate::service::pipeline::now_us;
use std::time::{Duration, Instant};

/// The I/O link as the snapshot shows it: the state's name; the detail says why it is not up,
/// or names the last exception of the last minute while up.
fn link_view(
    state: &LinkState,
    peer: String,
    last_exception: Option<(Exception, Instant)>,
    now: Instant,
) -> LinkView {
    let detail = match state {
        LinkState::Connecting { attempt } => Some(format!("attempt {attempt}")),
        LinkState::Up { .. } => last_exception
            .map(|(x, at)| (x, now.saturating_duration_since(at)))
            .filter(|(_, ago)| *ago <= Duration::from_secs(60))
            .map(|(x, ago)| format!("last {x} {:.1} s ago", ago.as_secs_f64())),
        LinkState::Closed => None,
        s => Some(s.to_string()),
    };
    LinkView {
        state: state.name().to_string(),
        peer,
        detail,
        ..LinkView::default()
    }
}

/// The CAN link as the snapshot shows it: up while the drive's heartbeat comes; the detail
/// names the drive's NMT state and the SYNC period in use (the quiet one at rest, see
/// `DriveConfig::quiet_sync_period`); the rate is the TPDOs the drive answers with per second.
fn can_view(st: &DriveStatus, peer: String, sync: (Duration, Duration), tpdo_hz: f64) -> LinkView {
    let mut detail = Vec::new();
    if let Some(n) = st.nmt {
        detail.push(format!("NMT {}", crate::canopen::nmt::state_name(n)));
    }
    if st.sync_running {
        detail.push(if st.sync_quiet {
            format!("SYNC {} ms (quiet at rest)", sync.1.as_millis())
        } else {
            format!("SYNC {} ms", sync.0.as_millis())
        });
    }
    LinkView {
        state: if st.heartbeat_ok {
            "up".into()
        } else {
            "no heartbeat".into()
        },
        peer,
        detail: (!detail.is_empty()).then(|| detail.join(", ")),
        rate_hz: tpdo_hz,
        ..LinkView::default()
    }
}

/// Events per second from a running count, over spans of at least `span` (the last complete
/// span; 0 before the first ends). Sans-I/O: time is an argument.
#[derive(Clone, Copy, Debug)]
pub(super) struct CountRate {
    span: Duration,
    since: Option<(Instant, u64)>,
    pub(super) rate_hz: f64,
}

impl CountRate {
    pub(super) fn new(span: Duration) -> Self {
        CountRate {
            span,
            since: None,
            rate_hz: 0.0,
        }
    }

    pub(super) fn update(&mut self, now: Instant, count: u64) -> f64 {
        match self.since {
            Some((t0, c0)) if now.saturating_duration_since(t0) >= self.span => {
                let dt = now.saturating_duration_since(t0).as_secs_f64();
                self.rate_hz = count.saturating_sub(c0) as f64 / dt;
                self.since = Some((now, count));
            }
            Some((_, c0)) if count < c0 => self.since = Some((now, count)),
            Some(_) => {}
            None => self.since = Some((now, count)),
        }
        self.rate_hz
    }
}

fn power_name(s: Option<PowerState>) -> String {
    s.map(|p| p.label().to_string())
        .unwrap_or_else(|| "unknown".into())
}

impl Core {
    /// The snapshot now.
    pub(super) fn build_snapshot(&self) -> Snapshot {
        let stats = self.acquisition.stats();
        let p = &self.pipeline;
        let now = crate::util::clock::now();
        let psd = p.last_frame.map(|f| PsdView {
            seq: f.seq,
            spots_um: f.spots.map(|s| s.map(|s| [s.x * 1e3, s.y * 1e3])),
            sums_v: f.sums,
            half_size_um: self.half_size_um,
            valid: f.is_valid() && self.acquisition.is_fresh(&f, now),
            age_ms: now.saturating_duration_since(f.at).as_secs_f64() * 1e3,
            rate_hz: stats.frames_per_s,
            invalid_frames: stats.invalid_frames,
            late_frames: p.late_frames,
        });
        let live = p.measure.live().map(|l| LiveView {
            errors: l.errors.to_user(),
            sd: l.sd.to_user(),
            frames: l.frames,
            travel_mm: l.travel_mm,
            nominal_mm: l.nominal,
            position_mm: l.position_mm,
            zeroed: l.zeroed,
        });
        let st = &self.drive_status;
        let stitch = p.tracker.stitch();
        let link_stats = self.acquisition.link().stats();
        let mut io = link_view(
            &self.acquisition.link().state().borrow(),
            self.acquisition.link().addr().to_string(),
            link_stats.last_exception,
            now,
        );
        io.exceptions = link_stats.exceptions;
        io.rate_hz = stats.frames_per_s;
        io.latency_p50_us = link_stats
            .latency_p50
            .map(|d| d.as_secs_f64() * 1e6)
            .unwrap_or(0.0);
        io.latency_p99_us = link_stats
            .latency_p99
            .map(|d| d.as_secs_f64() * 1e6)
            .unwrap_or(0.0);
        io.errors = link_stats.errors;
        io.reconnects = link_stats.reconnects;
        let can = can_view(
            st,
            self.can_peer.clone(),
            self.sync_periods,
            self.tpdo_rate.rate_hz,
        );
        let mut snap = Snapshot {
            unix_us: now_us(),
            psd,
            live,
            follower: FollowerView {
                node_id: self.node_id,
                state: power_name(st.state),
                position_mm: st.position_mm,
                target_mm: st.commanded_mm,
                homed: st.homed,
                heartbeat_ok: st.heartbeat_ok,
                last_emcy: st.last_emcy.map(|e| e.to_string()),
                busy: st.busy.map(str::to_string),
                busy_s: st
                    .busy_since
                    .map(|t| now.saturating_duration_since(t).as_secs_f64()),
            },
            tracking: TrackingView {
                strategy: stitch.strategy.name().into(),
                valid: stitch.valid,
                at_rest: p.tracker.at_rest(now),
                follower_mm: stitch.follower_mm,
                vertical_um: stitch.vertical_mm * 1e3,
                sd_um: stitch.variance.map(|v| v.sqrt() * 1e3),
                handovers: stitch.handovers,
                follower_map: self.follower_map.clone(),
            },
            links: LinksView { io, can },
            alarms: p.alarms.list().to_vec(),
            ..Snapshot::default()
        };
        for proc in &self.procedures {
            proc.show(&mut snap, &self.pipeline);
        }
        snap
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::canopen::{DriveStatus, NmtState};

    const SYNC: (Duration, Duration) = (Duration::from_millis(10), Duration::from_millis(100));

    #[test]
    fn the_can_link_names_nmt_and_the_sync_period_in_use() {
        let mut st = DriveStatus::default();
        let v = can_view(&st, "peer".into(), SYNC, 0.0);
        assert_eq!((v.state.as_str(), v.detail), ("no heartbeat", None));
        st.heartbeat_ok = true;
        st.nmt = Some(NmtState::Operational);
        st.sync_running = true;
        let v = can_view(&st, "peer".into(), SYNC, 100.0);
        assert_eq!(v.state, "up");
        assert_eq!(v.detail.as_deref(), Some("NMT Operational, SYNC 10 ms"));
        assert_eq!(v.rate_hz, 100.0);
        st.sync_quiet = true;
        let v = can_view(&st, "peer".into(), SYNC, 10.0);
        assert_eq!(
            v.detail.as_deref(),
            Some("NMT Operational, SYNC 100 ms (quiet at rest)")
        );
    }

    #[test]
    fn the_count_rate_is_over_whole_spans() {
        let t0 = crate::util::clock::now();
        let ms = Duration::from_millis;
        let mut r = CountRate::new(Duration::from_secs(1));
        assert_eq!(r.update(t0, 50), 0.0);
        // Within the span the last rate holds.
        assert_eq!(r.update(t0 + ms(500), 100), 0.0);
        // 125 TPDOs over 1.25 s.
        assert!((r.update(t0 + ms(1250), 175) - 100.0).abs() < 1e-9);
        assert!((r.update(t0 + ms(1900), 180) - 100.0).abs() < 1e-9);
        // 10 over the next 1 s: the quiet SYNC.
        assert!((r.update(t0 + ms(2250), 185) - 10.0).abs() < 1e-9);
        // A count that restarts (a new drive handle) starts a new span instead of going negative.
        assert!((r.update(t0 + ms(2500), 3) - 10.0).abs() < 1e-9);
        assert!((r.update(t0 + ms(3500), 13) - 10.0).abs() < 1e-9);
    }
}
