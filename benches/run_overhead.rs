//! A whole ISO 230-2 run on the twin through real processes (`axiscomp sim`, whose CNC runs
//! the part program, and `axiscomp serve`), its wall time against the plan's motion + dwell
//! time (issue 4, must-show 5: the software overhead, target < 2 %).
//!
//!   cargo bench --bench run_overhead                 # the default plan, 3 runs
//!   RUNS=1 PLAN="0,100,5,2,1.5,3000,1" cargo bench --bench run_overhead
//!
//! PLAN is start_mm,end_mm,targets,runs,dwell_s,feed_mm_min,overrun_mm. For each repetition it
//! prints: the floor (`Plan::motion_time_s` at the twin's 500 mm/s², dwell included); the wall
//! time from the `run_start` request to the run's state `finished`; the CNC's own program time
//! (the twin times its program from first block to end); the latency from the request to the
//! program running on the twin; the programs sent (more than one: make-up passes); and the
//! overhead (wall − floor) / floor. The run is finished when its last capture is stored, which
//! is before the last dwell ends: a run without software overhead comes out slightly below the
//! floor.

use axiscomp::run::{Plan, PlanSpec};
use axiscomp::service::api::Request;
use axiscomp::service::control::Client;
use std::net::{TcpListener, UdpSocket};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};

/// The twin carriage's acceleration (configs/sim.toml `[twin.carriage] accel_mm_s2`).
const ACCEL_MM_S2: f64 = 500.0;

struct Procs(Vec<Child>);

impl Drop for Procs {
    fn drop(&mut self) {
        for c in &mut self.0 {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

fn free_tcp() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("a free TCP port")
}

fn free_udp() -> u16 {
    UdpSocket::bind("127.0.0.1:0")
        .and_then(|s| s.local_addr())
        .map(|a| a.port())
        .expect("a free UDP port")
}

fn plan_from_env() -> PlanSpec {
    let text = std::env::var("PLAN").unwrap_or_else(|_| "0,100,5,2,1.5,3000,1".into());
    let v: Vec<f64> = text
        .split(',')
        .map(|x| x.trim().parse().expect("PLAN: numbers"))
        .collect();
    assert_eq!(v.len(), 7, "PLAN=start,end,targets,runs,dwell,feed,overrun");
    PlanSpec {
        axis: "X".into(),
        start_mm: v[0],
        end_mm: v[1],
        targets: v[2] as usize,
        runs: v[3] as u32,
        overrun_mm: v[6],
        dwell_s: v[4],
        feed_mm_min: v[5],
        lead_mm: 0.0,
        reference_mm: None,
    }
}

/// The repository's twin and service configurations with free ports and `dir` for state.
fn configs(dir: &Path) -> (PathBuf, PathBuf, String, PathBuf) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let (io, ctl, can_svc, can_twin) = (free_tcp(), free_tcp(), free_udp(), free_udp());
    let sim = std::fs::read_to_string(root.join("configs/sim.toml"))
        .expect("configs/sim.toml")
        .replace("127.0.0.1:5020", &format!("127.0.0.1:{io}"))
        .replace("127.0.0.1:5099", &format!("127.0.0.1:{ctl}"))
        .replace(
            "local = \"127.0.0.1:20001\"",
            &format!("local = \"127.0.0.1:{can_twin}\""),
        )
        .replace(
            "remote = \"127.0.0.1:20000\"",
            &format!("remote = \"127.0.0.1:{can_svc}\""),
        );
    let svc = std::fs::read_to_string(root.join("configs/twin-service.toml"))
        .expect("configs/twin-service.toml")
        .replace("./run/", &format!("{}/", dir.display()))
        .replace("127.0.0.1:5020", &format!("127.0.0.1:{io}"))
        .replace(
            "local = \"127.0.0.1:20000\"",
            &format!("local = \"127.0.0.1:{can_svc}\""),
        )
        .replace(
            "remote = \"127.0.0.1:20001\"",
            &format!("remote = \"127.0.0.1:{can_twin}\""),
        )
        + &format!("\n[cnc]\nmode = \"twin\"\ntwin = \"127.0.0.1:{ctl}\"\n")
        // The bench times a run, not the beam alignment a run needs first (the twin's head
        // is mounted square): the pre-run check is off.
        + "\n[align]\ncheck_before_run = false\n";
    let (sim_path, svc_path) = (dir.join("sim.toml"), dir.join("service.toml"));
    std::fs::write(&sim_path, sim).expect("write sim.toml");
    std::fs::write(&svc_path, svc).expect("write service.toml");
    (
        sim_path,
        svc_path,
        format!("127.0.0.1:{ctl}"),
        dir.join("control.sock"),
    )
}

fn spawn(args: &[&str], config: &Path, log: &Path) -> Child {
    let out = std::fs::File::create(log).expect("log");
    let err = out.try_clone().expect("log");
    Command::new(env!("CARGO_BIN_EXE_axiscomp"))
        .args(args)
        .arg("--config")
        .arg(config)
        .env("RUST_LOG", "warn")
        .stdin(Stdio::null())
        .stdout(out)
        .stderr(err)
        .spawn()
        .expect("spawn axiscomp")
}

/// The twin CNC's state (`{"cmd":"cnc"}` on its control socket).
async fn twin_cnc(addr: &str) -> Option<serde_json::Value> {
    let s = tokio::net::TcpStream::connect(addr).await.ok()?;
    let (rd, mut wr) = s.into_split();
    wr.write_all(b"{\"cmd\":\"cnc\"}\n").await.ok()?;
    let line = BufReader::new(rd).lines().next_line().await.ok()??;
    let v: serde_json::Value = serde_json::from_str(&line).ok()?;
    Some(v["cnc"].clone())
}

async fn ask(socket: &Path, req: &Request) -> Option<serde_json::Value> {
    let mut c = Client::connect(socket).await.ok()?;
    c.request(req).await.ok()
}

struct Figures {
    floor_s: f64,
    wall_s: f64,
    cnc_s: Option<f64>,
    latency_s: f64,
    programs: u64,
    captures: u64,
}

async fn one_run(spec: &PlanSpec) -> Result<Figures, String> {
    let dir = std::env::temp_dir().join(format!(
        "axiscomp-run-overhead-{}-{}",
        std::process::id(),
        free_tcp()
    ));
    std::fs::create_dir_all(&dir).map_err(|e| e.to_string())?;
    let (sim_cfg, svc_cfg, ctl, socket) = configs(&dir);
    let mut procs = Procs(vec![spawn(&["sim"], &sim_cfg, &dir.join("sim.log"))]);
    tokio::time::sleep(Duration::from_secs(1)).await;
    procs
        .0
        .push(spawn(&["serve"], &svc_cfg, &dir.join("serve.log")));
    // Up, the follower homed, the stitch referenced, at rest.
    let end = Instant::now() + Duration::from_secs(60);
    loop {
        if let Ok(mut c) = Client::connect(&socket).await
            && let Ok(s) = c.status().await
            && s.follower.homed
            && s.tracking.valid
            && s.tracking.at_rest
        {
            break;
        }
        if Instant::now() > end {
            return Err(format!(
                "the service did not come up; see {}",
                dir.display()
            ));
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let floor_s = Plan::new(spec.clone())
        .map_err(|e| e.to_string())?
        .motion_time_s(ACCEL_MM_S2);
    let before = twin_cnc(&ctl).await.and_then(|c| c["programs"].as_u64());
    let t0 = Instant::now();
    let started = ask(
        &socket,
        &Request::RunStart {
            plan: spec.clone(),
            dialect: Some("linuxcnc".into()),
            notes: Some("bench run_overhead".into()),
        },
    )
    .await
    .ok_or("run_start not answered")?;
    if started.get("run_id").is_none() {
        return Err(format!("run_start refused: {started}"));
    }
    // The program running on the twin (polled every 5 ms).
    let mut latency_s = f64::NAN;
    while t0.elapsed() < Duration::from_secs(10) {
        if twin_cnc(&ctl).await.and_then(|c| c["programs"].as_u64()) > before {
            latency_s = t0.elapsed().as_secs_f64();
            break;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    // The run finished (polled every 20 ms).
    let limit = Duration::from_secs_f64(3.0 * floor_s + 60.0);
    let (wall_s, status) = loop {
        let st = ask(&socket, &Request::RunStatus).await;
        let state = st.as_ref().and_then(|s| s["state"].as_str()).unwrap_or("");
        if !state.is_empty() && state != "running" {
            break (t0.elapsed().as_secs_f64(), st.unwrap_or_default());
        }
        if t0.elapsed() > limit {
            return Err(format!("no end within {limit:?}; see {}", dir.display()));
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    if status["state"] != "finished" {
        return Err(format!("the run ended so: {status}"));
    }
    // The twin's own program time, once its last program has ended.
    let mut cnc = None;
    let end = Instant::now() + Duration::from_secs_f64(2.0 * spec.dwell_s + 10.0);
    while Instant::now() < end {
        if let Some(c) = twin_cnc(&ctl).await
            && c["done"].as_bool() == Some(true)
        {
            cnc = Some(c);
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let programs = cnc
        .as_ref()
        .and_then(|c| c["programs"].as_u64())
        .unwrap_or(0)
        .saturating_sub(before.unwrap_or(0));
    drop(procs);
    let _ = std::fs::remove_dir_all(&dir);
    Ok(Figures {
        floor_s,
        wall_s,
        cnc_s: cnc.and_then(|c| c["last_program_s"].as_f64()),
        latency_s,
        programs,
        captures: status["captures"].as_u64().unwrap_or(0),
    })
}

fn main() {
    // `cargo bench` passes --bench; `cargo test --benches` would run this too: do nothing then.
    if !std::env::args().any(|a| a == "--bench") {
        return;
    }
    let runs: usize = std::env::var("RUNS")
        .ok()
        .and_then(|r| r.parse().ok())
        .unwrap_or(3);
    let spec = plan_from_env();
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    println!(
        "run_overhead: {} {}–{} mm, {} targets, {} runs, dwell {} s, feed {} mm/min, overrun {} mm",
        spec.axis,
        spec.start_mm,
        spec.end_mm,
        spec.targets,
        spec.runs,
        spec.dwell_s,
        spec.feed_mm_min,
        spec.overrun_mm
    );
    let mut overheads = Vec::new();
    for i in 0..runs {
        match rt.block_on(one_run(&spec)) {
            Ok(f) => {
                let overhead = (f.wall_s - f.floor_s) / f.floor_s * 100.0;
                overheads.push(overhead);
                println!(
                    "run_overhead {}: {} captures; floor (motion + dwell) {:.2} s; wall {:.2} s; CNC program {}; program start {:.0} ms; programs {}; overhead {:+.2} %",
                    i + 1,
                    f.captures,
                    f.floor_s,
                    f.wall_s,
                    f.cnc_s
                        .map(|s| format!("{s:.2} s"))
                        .unwrap_or_else(|| "?".into()),
                    f.latency_s * 1e3,
                    f.programs,
                    overhead
                );
            }
            Err(e) => println!("run_overhead {}: FAILED: {e}", i + 1),
        }
    }
    if !overheads.is_empty() {
        overheads.sort_by(f64::total_cmp);
        println!(
            "run_overhead: median overhead {:+.2} % over {} runs (min {:+.2} %, max {:+.2} %)",
            overheads[overheads.len() / 2],
            overheads.len(),
            overheads[0],
            overheads[overheads.len() - 1]
        );
    }
}
