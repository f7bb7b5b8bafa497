//! The twin's hexapod controller, speaking both protocols labs own on loopback: PI GCS 2.0
//! (a C-887, TCP port 50000) and Newport's XPS API (an HXP, TCP port 5001), over one shared
//! state, so `pipython`, `newportxps` and axiscomp's drivers all move the same platform. The
//! pose it reaches is what the twin's head sees ([`HexapodMount`], added to the moving
//! module's errors by the plant).
//!
//! Moves take time (per-axis speeds), reach the target within the platform's repeatability,
//! and are refused outside the workspace (GCS error 7, XPS error -17) or before referencing
//! (GCS 5, XPS -22). Faults, armed for a coming move: a controller error code, a following
//! error (GCS: the servo drops and `ERR?` says -1024; XPS: the move answers -25 and the group
//! is disabled until initialised again), and a dropped link (the connection is closed
//! without an answer).

use super::Rng;
use crate::hexapod::{AXES, HexPose, Workspace, gcs, wire_number, xps};
use crate::units::Errors6;
use std::collections::VecDeque;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::task::JoinHandle;

/// The pose the platform is at, as the plant sees it: a linear move between two poses.
#[derive(Debug)]
pub struct HexapodMount {
    motion: Mutex<Motion>,
}

#[derive(Clone, Copy, Debug)]
struct Motion {
    from: HexPose,
    to: HexPose,
    start: Instant,
    end: Instant,
}

impl Default for HexapodMount {
    fn default() -> Self {
        let now = crate::util::clock::now();
        HexapodMount {
            motion: Mutex::new(Motion {
                from: HexPose::default(),
                to: HexPose::default(),
                start: now,
                end: now,
            }),
        }
    }
}

impl HexapodMount {
    fn lock(&self) -> std::sync::MutexGuard<'_, Motion> {
        self.motion.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The platform's pose at `now`.
    pub fn pose_at(&self, now: Instant) -> HexPose {
        let m = *self.lock();
        if now >= m.end {
            return m.to;
        }
        let total = m.end.saturating_duration_since(m.start).as_secs_f64();
        let f = if total > 0.0 {
            now.saturating_duration_since(m.start).as_secs_f64() / total
        } else {
            1.0
        };
        HexPose(std::array::from_fn(|k| {
            m.from.0[k] + f * (m.to.0[k] - m.from.0[k])
        }))
    }

    /// Add the platform's pose at `now` to the moving module's errors (the plant's hook).
    pub fn apply(&self, errors: &mut Errors6, now: Instant) {
        let e = self.pose_at(now).to_errors().to_array();
        let mut a = errors.to_array();
        for k in 0..6 {
            a[k] += e[k];
        }
        *errors = Errors6::from_array(a);
    }

    /// Whether a move is under way at `now`.
    pub fn moving(&self, now: Instant) -> bool {
        now < self.lock().end
    }

    fn start_move(&self, to: HexPose, duration: Duration, now: Instant) {
        let from = self.pose_at(now);
        *self.lock() = Motion {
            from,
            to,
            start: now,
            end: now + duration,
        };
    }

    fn halt(&self, now: Instant) {
        let here = self.pose_at(now);
        *self.lock() = Motion {
            from: here,
            to: here,
            start: now,
            end: now,
        };
    }
}

/// A fault armed for a coming move.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum HexapodFault {
    /// The move is refused with this controller code (GCS positive codes, XPS negative).
    Error(i64),
    /// The move starts and fails with a following error.
    FollowingError,
    /// The connection is closed when the move is commanded, without an answer.
    DropLink,
}

/// What the twin hexapod is built from.
#[derive(Clone, Debug, PartialEq)]
pub struct TwinHexapodSpec {
    /// Where the GCS server listens (None: no server).
    pub gcs: Option<SocketAddr>,
    /// Where the XPS server listens (None: no server).
    pub xps: Option<SocketAddr>,
    pub workspace: Workspace,
    /// Speeds of the linear (mm/s) and angular (°/s) axes.
    pub speed_mm_s: f64,
    pub speed_deg_s: f64,
    /// Repeatability per axis (standard deviation, mm and degrees).
    pub repeatability: [f64; 6],
    pub seed: u64,
}

impl Default for TwinHexapodSpec {
    /// An HXP50-like platform: ±10 mm, ±5 mm vertical, ±7° (a box inside its real workspace),
    /// 2 mm/s and 1°/s, 0.1 µm / 0.1 µrad repeatability.
    fn default() -> Self {
        TwinHexapodSpec {
            gcs: Some(SocketAddr::from(([127, 0, 0, 1], 50000))),
            xps: Some(SocketAddr::from(([127, 0, 0, 1], 5001))),
            workspace: Workspace::symmetric([10.0, 10.0, 5.0, 7.0, 7.0, 7.0]),
            speed_mm_s: 2.0,
            speed_deg_s: 1.0,
            repeatability: [1e-4, 1e-4, 1e-4, 6e-6, 6e-6, 6e-6],
            seed: 1,
        }
    }
}

/// The twin's actuator profiles: acceleration (mm/s²) and jerk times (s).
const SGAMMA_ACCEL: f64 = 20.0;
const SGAMMA_JERK: (f64, f64) = (0.04, 0.2);
/// The platform's top linear speed (GCS `VLS`, XPS actuator velocity), mm/s.
const MAX_ACTUATOR_MM_S: f64 = 50.0;

/// XPS group states used here.
const NOT_INIT: i64 = 7;
const NOT_REFERENCED: i64 = 42;
const READY_HOMING: i64 = 11;
const READY_MOTION: i64 = 12;
const READY_ABORT: i64 = 10;
const MOVING: i64 = 44;
const DISABLED_FOLLOWING: i64 = 22;

/// The XPS error texts this twin uses (Newport's XPS/HXP manuals).
pub fn xps_error_text(code: i64) -> &'static str {
    match code {
        0 => "Successful command",
        -4 => "Unknown command",
        -9 => "Wrong number of parameters in the command",
        -17 => "Parameter out of range",
        -19 => "GroupName doesn't exist or unknown command",
        -22 => "Not allowed action",
        -25 => "Following Error",
        -26 => "Emergency signal",
        -27 => "Move Aborted",
        _ => "Unknown error",
    }
}

/// The XPS group state texts (`GroupStatusStringGet`).
pub fn xps_status_text(code: i64) -> &'static str {
    match code {
        NOT_INIT => "Not initialized state due to a GroupKill or KillAll command",
        READY_ABORT => "Ready state due to an AbortMove command",
        READY_HOMING => "Ready state from homing",
        READY_MOTION => "Ready state from motion",
        DISABLED_FOLLOWING => "Disabled state due to a following error during motion",
        NOT_REFERENCED => "Not referenced state",
        MOVING => "Moving state",
        _ => "Unknown group status",
    }
}

struct State {
    servo: bool,
    referenced: bool,
    /// XPS group state when not moving.
    group: i64,
    work: HexPose,
    pivot: [f64; 3],
    target: HexPose,
    /// GCS error register (cleared by `ERR?`).
    error: i64,
    velocity: f64,
    /// The actuators' SGamma parameters (XPS `HEXAPOD.1` to `.6`): velocity (mm/s),
    /// acceleration (mm/s²), minimum and maximum jerk time (s). The platform moves at the
    /// velocity last set.
    sgamma: [[f64; 4]; 6],
    faults: VecDeque<HexapodFault>,
    moves: usize,
    rng: Rng,
}

/// The twin hexapod: its state and the servers.
pub struct TwinHexapod {
    pub spec: TwinHexapodSpec,
    pub mount: Arc<HexapodMount>,
    state: Mutex<State>,
}

/// The running servers; dropping this stops them.
pub struct HexapodServers {
    pub hexapod: Arc<TwinHexapod>,
    pub gcs: Option<SocketAddr>,
    pub xps: Option<SocketAddr>,
    tasks: Vec<JoinHandle<()>>,
}

impl Drop for HexapodServers {
    fn drop(&mut self) {
        for t in &self.tasks {
            t.abort();
        }
    }
}

/// What a move request led to.
enum MoveOutcome {
    Started(Duration),
    Refused(i64),
    Following,
    Drop,
}

impl TwinHexapod {
    pub fn new(spec: TwinHexapodSpec, mount: Arc<HexapodMount>) -> Self {
        let rng = Rng::new(spec.seed).fork(40);
        TwinHexapod {
            state: Mutex::new(State {
                servo: false,
                referenced: false,
                group: NOT_INIT,
                work: HexPose::default(),
                pivot: [0.0; 3],
                target: HexPose::default(),
                error: 0,
                velocity: spec.speed_mm_s,
                sgamma: [[spec.speed_mm_s, SGAMMA_ACCEL, SGAMMA_JERK.0, SGAMMA_JERK.1]; 6],
                faults: VecDeque::new(),
                moves: 0,
                rng,
            }),
            spec,
            mount,
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Arm a fault for the next move.
    pub fn inject(&self, f: HexapodFault) {
        self.lock().faults.push_back(f);
    }

    /// Moves commanded so far (refused ones included).
    pub fn moves(&self) -> usize {
        self.lock().moves
    }

    /// The pivot point and work coordinate system last set.
    pub fn frames(&self) -> ([f64; 3], HexPose) {
        let s = self.lock();
        (s.pivot, s.work)
    }

    /// The reached pose now (work coordinates), as the controller's encoders see it.
    pub fn position(&self) -> HexPose {
        self.mount.pose_at(crate::util::clock::now())
    }

    fn home(&self) {
        let mut s = self.lock();
        s.referenced = true;
        s.servo = true;
        s.group = READY_HOMING;
        s.target = HexPose::default();
        drop(s);
        self.mount.start_move(
            HexPose::default(),
            Duration::ZERO,
            crate::util::clock::now(),
        );
    }

    fn request_move(&self, target: HexPose, gcs: bool) -> MoveOutcome {
        let now = crate::util::clock::now();
        let mut s = self.lock();
        s.moves += 1;
        let ready = if gcs {
            s.servo && s.referenced
        } else {
            xps::is_ready(s.group)
        };
        if !ready {
            return MoveOutcome::Refused(if gcs { 5 } else { -22 });
        }
        if self.spec.workspace.outside(&target).is_some() {
            return MoveOutcome::Refused(if gcs { 7 } else { -17 });
        }
        match s.faults.pop_front() {
            Some(HexapodFault::Error(code)) => return MoveOutcome::Refused(code),
            Some(HexapodFault::DropLink) => return MoveOutcome::Drop,
            Some(HexapodFault::FollowingError) => {
                s.servo = false;
                s.group = DISABLED_FOLLOWING;
                s.error = -1024;
                drop(s);
                self.mount.halt(now);
                return MoveOutcome::Following;
            }
            None => {}
        }
        let from = self.mount.pose_at(now);
        let rep = self.spec.repeatability;
        let reached = HexPose(std::array::from_fn(|k| target.0[k] + s.rng.gauss(rep[k])));
        let t = (0..6)
            .map(|k| {
                let v = if k < 3 {
                    s.velocity
                } else {
                    self.spec.speed_deg_s
                };
                (target.0[k] - from.0[k]).abs() / v.max(1e-9)
            })
            .fold(0.0, f64::max);
        s.target = target;
        s.group = READY_MOTION;
        drop(s);
        let d = Duration::from_secs_f64(t);
        self.mount.start_move(reached, d, now);
        MoveOutcome::Started(d)
    }

    fn stop(&self) {
        self.mount.halt(crate::util::clock::now());
        let mut s = self.lock();
        s.target = self.mount.pose_at(crate::util::clock::now());
        if s.group == READY_MOTION || s.group == READY_HOMING {
            s.group = READY_ABORT;
        }
    }
}

/// Start the servers the spec asks for on `mount` (the plant's). A port that cannot be bound
/// is reported as an error naming it.
pub async fn start(
    spec: TwinHexapodSpec,
    mount: Arc<HexapodMount>,
) -> Result<HexapodServers, String> {
    let hexapod = Arc::new(TwinHexapod::new(spec.clone(), mount));
    let mut servers = HexapodServers {
        hexapod: hexapod.clone(),
        gcs: None,
        xps: None,
        tasks: Vec::new(),
    };
    if let Some(bind) = spec.gcs {
        let l = TcpListener::bind(bind)
            .await
            .map_err(|e| format!("twin hexapod GCS server on {bind}: {e}"))?;
        servers.gcs = l.local_addr().ok();
        let h = hexapod.clone();
        servers.tasks.push(tokio::spawn(accept(l, h, true)));
    }
    if let Some(bind) = spec.xps {
        let l = TcpListener::bind(bind)
            .await
            .map_err(|e| format!("twin hexapod XPS server on {bind}: {e}"))?;
        servers.xps = l.local_addr().ok();
        let h = hexapod.clone();
        servers.tasks.push(tokio::spawn(accept(l, h, false)));
    }
    Ok(servers)
}

async fn accept(l: TcpListener, h: Arc<TwinHexapod>, gcs: bool) {
    loop {
        let Ok((s, _)) = l.accept().await else {
            continue;
        };
        let _ = s.set_nodelay(true);
        let h = h.clone();
        tokio::spawn(async move {
            if gcs {
                serve_gcs(s, h).await
            } else {
                serve_xps(s, h).await
            }
        });
    }
}

// ---------- GCS 2.0 ----------

fn gcs_axes_answer(values: &[f64; 6], axes: &[usize], int: bool) -> String {
    let lines: Vec<String> = axes
        .iter()
        .map(|&k| {
            if int {
                format!("{}={}", AXES[k], values[k] as i64)
            } else {
                format!("{}={:.7}", AXES[k], values[k])
            }
        })
        .collect();
    format!("{}\n", lines.join(" \n"))
}

/// The axes named in a query (all six when none).
fn gcs_axes(args: &[&str]) -> Option<Vec<usize>> {
    if args.is_empty() {
        return Some((0..6).collect());
    }
    args.iter()
        .map(|a| AXES.iter().position(|x| x == a))
        .collect()
}

/// `X 1 Y 2`-style pairs.
fn gcs_pairs(args: &[&str], names: &[&str]) -> Option<Vec<(usize, f64)>> {
    if args.is_empty() || !args.len().is_multiple_of(2) {
        return None;
    }
    args.chunks(2)
        .map(|c| Some((names.iter().position(|x| *x == c[0])?, c[1].parse().ok()?)))
        .collect()
}

/// One GCS line in, the answer out (None: no answer; Err: close the link).
fn gcs_line(h: &TwinHexapod, line: &str) -> Result<Option<String>, ()> {
    let mut words = line.split_whitespace();
    let Some(cmd) = words.next() else {
        return Ok(None);
    };
    let args: Vec<&str> = words.collect();
    let now = crate::util::clock::now();
    let set_error = |code: i64| {
        let mut s = h.lock();
        if s.error == 0 {
            s.error = code;
        }
    };
    let answer = match cmd.to_ascii_uppercase().as_str() {
        "*IDN?" => Some("(c)2026 axiscomp, C-887 twin, 0, 2.0\n".to_string()),
        "CSV?" => Some("2.0\n".into()),
        "ERR?" => {
            let mut s = h.lock();
            let e = s.error;
            s.error = 0;
            Some(format!("{e}\n"))
        }
        "SAI?" => Some(format!("{}\n", AXES.join(" \n"))),
        "SVO" => {
            match gcs_pairs(&args, &AXES) {
                Some(p) => {
                    let mut s = h.lock();
                    s.servo = p.iter().all(|(_, v)| *v == 1.0);
                    if s.servo && s.error == -1024 {
                        s.error = 0;
                    }
                }
                None => set_error(1),
            }
            None
        }
        "SVO?" => {
            let servo = if h.lock().servo { 1.0 } else { 0.0 };
            match gcs_axes(&args) {
                Some(a) => Some(gcs_axes_answer(&[servo; 6], &a, true)),
                None => {
                    set_error(15);
                    None
                }
            }
        }
        "FRF" => {
            if h.lock().servo {
                h.home();
            } else {
                set_error(5);
            }
            None
        }
        "FRF?" => {
            let r = if h.lock().referenced { 1.0 } else { 0.0 };
            gcs_axes(&args).map(|a| gcs_axes_answer(&[r; 6], &a, true))
        }
        "MOV" => {
            match gcs_pairs(&args, &AXES) {
                Some(p) => {
                    let mut target = h.lock().target;
                    for (k, v) in p {
                        target.0[k] = v;
                    }
                    match h.request_move(target, true) {
                        MoveOutcome::Started(_) | MoveOutcome::Following => {}
                        MoveOutcome::Refused(code) => set_error(code),
                        MoveOutcome::Drop => return Err(()),
                    }
                }
                None => set_error(1),
            }
            None
        }
        "MOV?" => {
            let t = h.lock().target;
            gcs_axes(&args).map(|a| gcs_axes_answer(&t.0, &a, false))
        }
        "POS?" => {
            let p = h.mount.pose_at(now);
            gcs_axes(&args).map(|a| gcs_axes_answer(&p.0, &a, false))
        }
        "ONT?" => {
            let on = {
                let s = h.lock();
                s.servo && !h.mount.moving(now)
            };
            let v = if on { 1.0 } else { 0.0 };
            gcs_axes(&args).map(|a| gcs_axes_answer(&[v; 6], &a, true))
        }
        "SPI" => {
            match gcs_pairs(&args, &["R", "S", "T"]) {
                Some(p) => {
                    let pose = h.mount.pose_at(now);
                    if pose.0[3..].iter().any(|v| *v != 0.0) {
                        set_error(9);
                    } else {
                        let mut s = h.lock();
                        for (k, v) in p {
                            s.pivot[k] = v;
                        }
                    }
                }
                None => set_error(1),
            }
            None
        }
        "SPI?" => {
            let p = h.lock().pivot;
            Some(format!("R={:.7} \nS={:.7} \nT={:.7}\n", p[0], p[1], p[2]))
        }
        "KSD" => {
            match args.split_first() {
                Some((_name, rest)) => match gcs_pairs(rest, &AXES) {
                    Some(p) => {
                        let mut s = h.lock();
                        for (k, v) in p {
                            s.work.0[k] = v;
                        }
                    }
                    None => set_error(1),
                },
                None => set_error(1),
            }
            None
        }
        "KEN" => {
            if args.len() != 1 {
                set_error(1);
            }
            None
        }
        "STP" | "HLT" => {
            h.stop();
            set_error(10);
            None
        }
        "VLS" => {
            match args.first().and_then(|v| v.parse::<f64>().ok()) {
                Some(v) if v > 0.0 && v <= MAX_ACTUATOR_MM_S => h.lock().velocity = v,
                _ => set_error(17),
            }
            None
        }
        "VLS?" => Some(format!("{:.7}\n", h.lock().velocity)),
        _ => {
            set_error(2);
            None
        }
    };
    Ok(answer)
}

async fn serve_gcs(mut s: TcpStream, h: Arc<TwinHexapod>) {
    let mut buf = [0u8; 4096];
    let mut line: Vec<u8> = Vec::new();
    loop {
        let n = match s.read(&mut buf).await {
            Ok(0) | Err(_) => return,
            Ok(n) => n,
        };
        for &b in &buf[..n] {
            // Single-character commands (no LF): #5 motion status, #7 ready, #24 stop.
            if line.is_empty() && matches!(b, 4 | 5 | 7 | 24) {
                let reply = match b {
                    5 => {
                        let m = if h.mount.moving(crate::util::clock::now()) {
                            63
                        } else {
                            0
                        };
                        Some(format!("{m}\n").into_bytes())
                    }
                    7 => Some(vec![0xB1, b'\n']),
                    24 => {
                        h.stop();
                        h.lock().error = 10;
                        None
                    }
                    _ => Some(b"0\n".to_vec()),
                };
                if let Some(r) = reply
                    && s.write_all(&r).await.is_err()
                {
                    return;
                }
                continue;
            }
            if b != b'\n' {
                line.push(b);
                continue;
            }
            let text = String::from_utf8_lossy(&line).into_owned();
            line.clear();
            match gcs_line(&h, text.trim_end_matches('\r')) {
                Ok(Some(a)) => {
                    if s.write_all(a.as_bytes()).await.is_err() {
                        return;
                    }
                }
                Ok(None) => {}
                Err(()) => return,
            }
        }
    }
}

// ---------- XPS ----------

/// Split `Name(a,b,c)` into the name and its arguments.
fn xps_call(text: &str) -> Option<(&str, Vec<&str>)> {
    let open = text.find('(')?;
    let inner = text[open + 1..].strip_suffix(')')?;
    let args = if inner.trim().is_empty() {
        Vec::new()
    } else {
        inner.split(',').map(str::trim).collect()
    };
    Some((text[..open].trim(), args))
}

fn nums(args: &[&str]) -> Option<[f64; 6]> {
    let v: Vec<f64> = args
        .iter()
        .map(|a| a.parse().ok())
        .collect::<Option<Vec<_>>>()?;
    v.try_into().ok()
}

/// One XPS call in, the answer out (Err: close the link). Moves block until done.
async fn xps_answer(h: &TwinHexapod, text: &str) -> Result<String, ()> {
    let reply = |code: i64, out: &str| format!("{code},{out},EndOfAPI");
    let Some((name, args)) = xps_call(text) else {
        return Ok(reply(-7, ""));
    };
    let group_ok = |i: usize| args.get(i).is_some_and(|g| *g == "HEXAPOD");
    let now = crate::util::clock::now();
    let status = |h: &TwinHexapod| {
        if h.mount.moving(crate::util::clock::now()) {
            MOVING
        } else {
            h.lock().group
        }
    };
    let out = match name {
        "FirmwareVersionGet" => reply(0, "HXP twin (axiscomp) 2.0"),
        "ErrorStringGet" => match args.first().and_then(|c| c.parse::<i64>().ok()) {
            Some(c) => reply(0, xps_error_text(c)),
            None => reply(-7, ""),
        },
        "GroupStatusStringGet" => match args.first().and_then(|c| c.parse::<i64>().ok()) {
            Some(c) => reply(0, xps_status_text(c)),
            None => reply(-7, ""),
        },
        "PositionerSGammaParametersGet" | "PositionerSGammaParametersSet" => {
            // The actuators: HEXAPOD.1 to HEXAPOD.6.
            let Some(n) = args
                .first()
                .and_then(|p| p.strip_prefix("HEXAPOD."))
                .and_then(|n| n.parse::<usize>().ok())
                .filter(|n| (1..=6).contains(n))
            else {
                return Ok(reply(-19, ""));
            };
            if name.ends_with("Get") {
                if args.len() != 5 {
                    return Ok(reply(-9, ""));
                }
                let p = h.lock().sgamma[n - 1];
                return Ok(reply(0, &p.map(wire_number).join(",")));
            }
            let v: Option<Vec<f64>> = args[1..].iter().map(|a| a.parse().ok()).collect();
            match v.as_deref() {
                Some(&[vel, acc, tmin, tmax]) => {
                    if !(vel > 0.0 && vel <= MAX_ACTUATOR_MM_S && acc > 0.0 && tmin > 0.0)
                        || tmax < tmin
                    {
                        return Ok(reply(-17, ""));
                    }
                    let mut s = h.lock();
                    s.sgamma[n - 1] = [vel, acc, tmin, tmax];
                    s.velocity = vel;
                    reply(0, "")
                }
                _ => reply(-9, ""),
            }
        }
        _ if !group_ok(0) => reply(-19, ""),
        "GroupKill" => {
            h.stop();
            let mut s = h.lock();
            s.group = NOT_INIT;
            s.servo = false;
            s.referenced = false;
            reply(0, "")
        }
        "GroupInitialize" => {
            let mut s = h.lock();
            if s.group == NOT_INIT || s.group == DISABLED_FOLLOWING {
                s.group = NOT_REFERENCED;
                s.servo = true;
                reply(0, "")
            } else {
                reply(-22, "")
            }
        }
        "GroupHomeSearch" => {
            if h.lock().group == NOT_REFERENCED {
                h.home();
                reply(0, "")
            } else {
                reply(-22, "")
            }
        }
        "GroupStatusGet" => reply(0, &status(h).to_string()),
        "GroupMoveAbort" => {
            h.stop();
            reply(0, "")
        }
        "HexapodCoordinateSystemSet" => {
            match (args.get(1).copied(), nums(&args[2.min(args.len())..])) {
                (Some(cs @ ("Work" | "Tool")), Some(v)) => {
                    let mut s = h.lock();
                    if cs == "Work" {
                        s.work = HexPose(v);
                    } else {
                        s.pivot = [v[0], v[1], v[2]];
                    }
                    reply(0, "")
                }
                (Some(_), Some(_)) => reply(-17, ""),
                _ => reply(-9, ""),
            }
        }
        "HexapodCoordinateSystemGet" => {
            let s = h.lock();
            let v = match args.get(1).copied() {
                Some("Work") => s.work.0,
                Some("Tool") => [s.pivot[0], s.pivot[1], s.pivot[2], 0.0, 0.0, 0.0],
                _ => return Ok(reply(-17, "")),
            };
            reply(0, &HexPose(v).0.map(wire_number).join(","))
        }
        "HexapodMoveAbsolute" => {
            if args.get(1).copied() != Some("Work") {
                return Ok(reply(-17, ""));
            }
            let Some(v) = nums(&args[2.min(args.len())..]) else {
                return Ok(reply(-9, ""));
            };
            match h.request_move(HexPose(v), false) {
                MoveOutcome::Started(d) => {
                    tokio::time::sleep(d).await;
                    reply(0, "")
                }
                MoveOutcome::Refused(code) => reply(code, ""),
                MoveOutcome::Following => reply(-25, ""),
                MoveOutcome::Drop => return Err(()),
            }
        }
        "HexapodPositionCurrentGet" => {
            if args.get(1).copied() != Some("Work") {
                return Ok(reply(-17, ""));
            }
            let p = h.mount.pose_at(now);
            reply(0, &p.0.map(|v| format!("{v:.7}")).join(","))
        }
        _ => reply(-4, ""),
    };
    Ok(out)
}

async fn serve_xps(mut s: TcpStream, h: Arc<TwinHexapod>) {
    let mut buf = [0u8; 4096];
    let mut pending = String::new();
    loop {
        let n = match s.read(&mut buf).await {
            Ok(0) | Err(_) => return,
            Ok(n) => n,
        };
        pending.push_str(&String::from_utf8_lossy(&buf[..n]));
        // Calls are not delimited: each ends at its closing parenthesis.
        while let Some(end) = pending.find(')') {
            let call: String = pending.drain(..=end).collect();
            match xps_answer(&h, call.trim()).await {
                Ok(a) => {
                    if s.write_all(a.as_bytes()).await.is_err() {
                        return;
                    }
                }
                Err(()) => return,
            }
        }
    }
}

/// The GCS error text the twin's controller would report (for tests).
pub fn gcs_error_text(code: i64) -> &'static str {
    gcs::error_text(code)
}

/// The twin's `[hexapod]` section as written (`configs/sim.toml`).
#[derive(Debug, Default, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
struct RawTwinHexapod {
    gcs_listen: Option<String>,
    xps_listen: Option<String>,
    workspace: Option<Vec<f64>>,
    speed_mm_s: Option<f64>,
    speed_deg_s: Option<f64>,
}

/// The twin hexapod's spec from the twin's configuration text: `[hexapod]` when present, else
/// the defaults (GCS on 127.0.0.1:50000, XPS on 127.0.0.1:5001, where the real controllers
/// listen). An empty address turns that server off. `label` names the file in errors.
pub fn spec_from_config(text: &str, label: &str) -> Result<TwinHexapodSpec, String> {
    #[derive(serde::Deserialize)]
    struct Outer {
        #[serde(default)]
        hexapod: Option<toml::Value>,
    }
    let bad = |key: &str, problem: String| format!("twin config {label}: hexapod.{key}: {problem}");
    let outer: Outer = toml::from_str(text).map_err(|e| format!("twin config {label}: {e}"))?;
    let raw: RawTwinHexapod = match outer.hexapod {
        Some(v) => v
            .try_into()
            .map_err(|e| format!("twin config {label}: [hexapod]: {e}"))?,
        None => RawTwinHexapod::default(),
    };
    let mut spec = TwinHexapodSpec::default();
    let addr = |key: &str, v: &Option<String>, dflt: Option<SocketAddr>| match v.as_deref() {
        None => Ok(dflt),
        Some("") => Ok(None),
        Some(s) => s.parse().map(Some).map_err(|_| {
            bad(
                key,
                format!("\"{s}\" is not IP:port, e.g. \"127.0.0.1:50000\""),
            )
        }),
    };
    spec.gcs = addr("gcs_listen", &raw.gcs_listen, spec.gcs)?;
    spec.xps = addr("xps_listen", &raw.xps_listen, spec.xps)?;
    use crate::util::range::Range;
    if let Some(w) = raw.workspace {
        let (mm, deg) = (
            Range::new(0.001, 1000.0, "mm"),
            Range::new(0.001, 90.0, "degrees"),
        );
        if w.len() != 6
            || w.iter()
                .enumerate()
                .any(|(k, x)| !if k < 3 { mm } else { deg }.contains(*x))
        {
            return Err(bad(
                "workspace",
                format!(
                    "give six half-ranges: {} for x, y, z and {} for u, v, w",
                    mm.describe(),
                    deg.describe()
                ),
            ));
        }
        spec.workspace = Workspace::symmetric(std::array::from_fn(|k| w[k]));
    }
    for (key, v, slot, unit) in [
        ("speed_mm_s", raw.speed_mm_s, &mut spec.speed_mm_s, "mm/s"),
        (
            "speed_deg_s",
            raw.speed_deg_s,
            &mut spec.speed_deg_s,
            "degrees/s",
        ),
    ] {
        if let Some(v) = v {
            *slot = Range::new(0.001, 1000.0, unit)
                .check(v)
                .map_err(|p| bad(key, p))?;
        }
    }
    Ok(spec)
}
