//! The command-line contracts and their bad-input behaviour (must show 4).

use crate::helpers::{TempDir, reference_layout_text, run, stderr, stdout};
use axiscomp::Errors6;
use axiscomp::optics::{Layout, Pose};
use serde_json::Value;

/// A failure that names the problem on one line, exits with 2 and does not panic.
fn assert_input_error(o: &std::process::Output, needles: &[&str]) {
    let err = stderr(o);
    assert_eq!(o.status.code(), Some(2), "exit code; stderr: {err}");
    assert!(!err.contains("panicked"), "{err}");
    let last = err.lines().last().unwrap_or_default();
    for n in needles {
        assert!(last.contains(n), "expected {n:?} in {last:?}");
    }
}

#[test]
fn optics_trace_contract() {
    let input = concat!(
        r#"{"errors":[1.5,-2,3,4,-5,6],"travel_mm":50,"follower_mm":49.5}"#,
        "\n",
        r#"{"errors":[0,0,0,0,0,0],"travel_mm":10,"follower_mm":0}"#,
        "\n"
    );
    let o = run(&["optics", "trace"], input);
    assert!(o.status.success(), "{}", stderr(&o));
    let lines: Vec<Value> = stdout(&o)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 2);

    let layout = Layout::reference();
    let want = layout
        .forward(&Pose::new(
            Errors6::from_user([1.5, -2.0, 3.0, 4.0, -5.0, 6.0]),
            50.0,
            49.5,
        ))
        .vector()
        .unwrap();
    let got = lines[0]["readings_um"].as_array().unwrap();
    for k in 0..6 {
        let g = got[k].as_f64().unwrap();
        assert!((g - want[k] * 1000.0).abs() < 1e-9, "reading {k}: {g}");
    }
    assert_eq!(lines[0]["valid"], serde_json::json!([true, true, true]));
    assert_eq!(lines[0]["reasons"], serde_json::json!([null, null, null]));

    // 10 mm of travel with the follower at 0: the spot is off PSD2.
    assert_eq!(lines[1]["valid"], serde_json::json!([true, false, true]));
    assert!(lines[1]["readings_um"][2].is_null() && lines[1]["readings_um"][3].is_null());
    let reason = lines[1]["reasons"][1].as_str().unwrap();
    assert!(reason.contains("off PSD2 active area"), "{reason}");
}

#[test]
fn optics_trace_bad_lines_are_named_and_the_rest_go_on() {
    let input = [
        "not json",
        r#"{"errors":[1,2,3]}"#,
        r#"{"errors":[1,2,3,4,5,"x"],"travel_mm":0,"follower_mm":0}"#,
        r#"{"errors":[0,0,0,0,0,0],"travel_mm":"a"}"#,
        r#"{"errors":[0,0,0,0,0,0],"speed":1}"#,
        r#"[1,2]"#,
        r#"{"errors":[0,0,0,0,0,0],"travel_mm":0,"follower_mm":0}"#,
    ]
    .join("\n");
    let o = run(&["optics", "trace"], &input);
    assert_eq!(o.status.code(), Some(2));
    let out: Vec<Value> = stdout(&o)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(out.len(), 7, "one output line per input line");
    let errs: Vec<String> = out[..6]
        .iter()
        .map(|v| v["error"].as_str().unwrap().to_string())
        .collect();
    assert!(errs[0].starts_with("line 1: not valid JSON"), "{}", errs[0]);
    assert!(errs[1].contains("line 2: field \"errors\": expected 6 numbers, found 3"));
    assert!(
        errs[2].contains("line 3: field \"errors\" item 6 (ez)"),
        "{}",
        errs[2]
    );
    assert!(
        errs[3].contains("line 4: field \"travel_mm\""),
        "{}",
        errs[3]
    );
    assert!(
        errs[4].contains("line 5: unknown field \"speed\""),
        "{}",
        errs[4]
    );
    assert!(
        errs[5].contains("line 6: expected a JSON object"),
        "{}",
        errs[5]
    );
    assert!(
        out[6]["readings_um"].is_array(),
        "the good line after them is traced"
    );
    let err = stderr(&o);
    assert!(
        err.contains("standard input line 3: field \"errors\" item 6"),
        "{err}"
    );
    assert!(!err.contains("panicked"));
}

#[test]
fn optics_jacobian_reports_design_figures() {
    let o = run(&["optics", "jacobian", "--json"], "");
    assert!(o.status.success(), "{}", stderr(&o));
    let v: Value = serde_json::from_str(stdout(&o).trim()).unwrap();
    let cond = v["condition_number"].as_f64().unwrap();
    assert!((cond - 5.6).abs() < 0.05, "{cond}");
    assert!((v["crlb"]["ey"].as_f64().unwrap() - 1.4046).abs() < 1e-3);
    assert!((v["jacobian"][3][4].as_f64().unwrap() - 0.72722).abs() < 1e-5);
    let o = run(&["optics", "jacobian", "--travel-mm", "100"], "");
    let text = stdout(&o);
    assert!(text.contains("condition number"), "{text}");
    assert!(text.contains("Cramér–Rao bound for σ = 1 µm"), "{text}");
}

#[test]
fn simulate_fit_decouple_round_trip() {
    let dir = TempDir::new("roundtrip");
    let poses = dir.path("poses.csv");
    let cal = dir.path("cal.toml");
    let o = run(
        &[
            "calibrate",
            "simulate",
            "--poses",
            "150",
            "--seed",
            "3",
            "--output",
            poses.to_str().unwrap(),
        ],
        "",
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let o = run(
        &[
            "calibrate",
            "fit",
            "--input",
            poses.to_str().unwrap(),
            "--output",
            cal.to_str().unwrap(),
        ],
        "",
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let report = stdout(&o);
    assert!(report.contains("rank 7 of 7"), "{report}");
    assert!(report.contains("hold-out RMS, model"), "{report}");
    let cal_text = std::fs::read_to_string(&cal).unwrap();
    for key in [
        "layout_hash",
        "created",
        "condition_number",
        "residual_rms_um",
        "[model.install.",
    ] {
        assert!(cal_text.contains(key), "calibration file lacks {key}");
    }

    // Decouple the pose set's own readings and compare with the poses it was made from.
    let text = std::fs::read_to_string(&poses).unwrap();
    let samples = axiscomp::calibrate::parse_pose_csv(&text, "poses").unwrap();
    let mut input = String::from("X1_um,Y1_um,X2_um,Y2_um,X3_um,Y3_um,travel_mm,follower_mm\n");
    for s in samples.iter().take(40) {
        let r: Vec<String> = s
            .readings
            .iter()
            .map(|x| format!("{:.6}", x * 1000.0))
            .collect();
        input += &format!("{},{},{}\n", r.join(","), s.pose.travel, s.pose.follower);
    }
    let o = run(
        &["decouple", "--calibration", cal.to_str().unwrap()],
        &input,
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    let mut lines = out.lines();
    assert!(
        lines
            .next()
            .unwrap()
            .starts_with("dx_um,dy_um,dz_um,ex_arcsec,ey_arcsec,ez_arcsec,sd_dx_um")
    );
    let mut worst: f64 = 0.0;
    for (line, s) in lines.zip(&samples) {
        let v: Vec<f64> = line.split(',').map(|f| f.parse().unwrap()).collect();
        let truth = s.pose.errors.to_user();
        for k in 0..6 {
            let sd = v[6 + k];
            assert!(sd > 0.0);
            worst = worst.max((v[k] - truth[k]).abs() / sd);
        }
    }
    assert!(worst < 5.0, "worst |error| / sd = {worst}");

    // The simulated model decodes noise-free readings exactly.
    let o = run(
        &["decouple", "--simulated"],
        "X1_um,Y1_um,X2_um,Y2_um,X3_um,Y3_um\n0,0,0,0,0,0\n",
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let row: Vec<f64> = stdout(&o)
        .lines()
        .nth(1)
        .unwrap()
        .split(',')
        .map(|f| f.parse().unwrap())
        .collect();
    assert!(row[..6].iter().all(|x| x.abs() < 1e-9), "{row:?}");
    assert!(
        (row[6] - 0.5).abs() < 1e-3,
        "sd of dx for σ = 1 µm: {}",
        row[6]
    );
}

#[test]
fn malformed_layouts_are_named() {
    let dir = TempDir::new("layouts");
    let good = reference_layout_text();
    let cases: Vec<(String, Vec<&str>)> = vec![
        (
            good.replacen("u = [0.0, 0.0, 1.0]", "u = [0.0, 0.5, 1.0]", 1),
            vec!["element BS1", "not orthonormal"],
        ),
        (
            good.replacen("[\"BS2\", \"reflect\"]", "[\"BS9\", \"reflect\"]", 1),
            vec!["path P1 step 5 (BS9 reflect)", "unknown element"],
        ),
        (
            good.replacen(
                "    [\"QWP\", \"qwp\"],\n    [\"PBS\", \"pbs_reflect\"],",
                "    [\"PBS\", \"pbs_reflect\"],",
                1,
            ),
            vec!["PBS pbs_reflect", "reflects only S"],
        ),
        (
            good.replacen("aperture_mm = 12.7", "aperture_mm = -1", 1),
            vec!["element BS1", "aperture_mm"],
        ),
        (
            good.replacen(
                "reading_paths = [\"P1\", \"P2\", \"P3\"]",
                "reading_paths = [\"P1\", \"P2\"]",
                1,
            ),
            vec!["reading_paths lists 2 paths"],
        ),
        (
            good.replacen("name = \"reference\"", "name = reference", 1),
            vec!["line 12"],
        ),
        (
            good.replacen("kind = \"psd\"", "kind = \"ccd\"", 1),
            vec!["element PSD1", "kind \"ccd\""],
        ),
    ];
    for (i, (text, needles)) in cases.iter().enumerate() {
        assert_ne!(text, &good, "case {i} did not change the layout");
        let p = dir.write(&format!("bad{i}.toml"), text);
        let o = run(&["optics", "jacobian", "--layout", p.to_str().unwrap()], "");
        assert_input_error(&o, needles);
        assert_eq!(stderr(&o).lines().count(), 1, "one line: {}", stderr(&o));
    }
    let o = run(
        &["optics", "trace", "--layout", "/nonexistent/layout.toml"],
        "",
    );
    assert_input_error(&o, &["/nonexistent/layout.toml", "cannot read"]);
}

#[test]
fn malformed_csv_inputs_are_named() {
    let dir = TempDir::new("csv");
    let header =
        "dx_um,dy_um,dz_um,ex_arcsec,ey_arcsec,ez_arcsec,X1_um,Y1_um,X2_um,Y2_um,X3_um,Y3_um";
    let bad_field = dir.write(
        "bad_field.csv",
        &format!("{header}\n0,0,0,0,0,0,0,0,0,0,0,0\n0,0,0,0,0,0,abc,0,0,0,0,0\n"),
    );
    let out = dir.path("cal.toml");
    let fit = |input: &std::path::Path| {
        run(
            &[
                "calibrate",
                "fit",
                "--input",
                input.to_str().unwrap(),
                "--output",
                out.to_str().unwrap(),
            ],
            "",
        )
    };
    assert_input_error(
        &fit(&bad_field),
        &[
            "bad_field.csv line 3, column X1_um",
            "\"abc\" is not a number",
        ],
    );
    let short = dir.write("short.csv", &format!("{header}\n0,0,0\n"));
    assert_input_error(
        &fit(&short),
        &["short.csv line 2: 3 fields, the header has 12"],
    );
    let missing = dir.write("missing.csv", "dx_um,dy_um\n1,2\n");
    assert_input_error(&fit(&missing), &["missing column \"dz_um\""]);
    let few = dir.write("few.csv", &format!("{header}\n0,0,0,0,0,0,0,0,0,0,0,0\n"));
    assert_input_error(&fit(&few), &["too few"]);
    assert!(!out.exists(), "no calibration written from bad input");

    let o = run(
        &["decouple", "--simulated"],
        "X1_um,Y1_um,X2_um,Y2_um,X3_um\n1,2,3,4,5\n",
    );
    assert_input_error(&o, &["standard input line 1", "missing column \"Y3_um\""]);
    let o = run(
        &["decouple", "--simulated"],
        "X1_um,Y1_um,X2_um,Y2_um,X3_um,Y3_um\n1,2,3,4,5,\n",
    );
    assert_input_error(&o, &["standard input line 2, column Y3_um: empty field"]);
    assert!(
        stdout(&o).is_empty(),
        "nothing written before the input is valid"
    );
}

#[test]
fn calibration_files_are_checked() {
    let dir = TempDir::new("calfiles");
    let cal = dir.write("garbage.toml", "[meta]\nformat = \"one\"\n");
    let o = run(
        &["decouple", "--calibration", cal.to_str().unwrap()],
        "X1_um,Y1_um,X2_um,Y2_um,X3_um,Y3_um\n",
    );
    assert_input_error(&o, &["calibration file", "garbage.toml", "line 2"]);

    // A calibration made for one layout refuses another.
    let poses = dir.path("p.csv");
    let good = dir.path("good.toml");
    assert!(
        run(
            &[
                "calibrate",
                "simulate",
                "--poses",
                "60",
                "--seed",
                "1",
                "--output",
                poses.to_str().unwrap()
            ],
            ""
        )
        .status
        .success()
    );
    assert!(
        run(
            &[
                "calibrate",
                "fit",
                "--method",
                "linear",
                "--input",
                poses.to_str().unwrap(),
                "--output",
                good.to_str().unwrap()
            ],
            ""
        )
        .status
        .success()
    );
    let other = dir.write(
        "other.toml",
        &reference_layout_text().replacen(
            "origin_mm = [-60.0, -340.0, 0.0]",
            "origin_mm = [-61.0, -340.0, 0.0]",
            1,
        ),
    );
    let o = run(
        &[
            "decouple",
            "--calibration",
            good.to_str().unwrap(),
            "--layout",
            other.to_str().unwrap(),
        ],
        "X1_um,Y1_um,X2_um,Y2_um,X3_um,Y3_um\n",
    );
    assert_input_error(&o, &["made for layout reference", "calibrate again"]);
}

#[test]
fn bad_numbers_on_the_command_line() {
    let o = run(&["optics", "jacobian", "--sigma-um=-1"], "");
    assert_input_error(&o, &["--sigma-um -1"]);
    let o = run(
        &[
            "calibrate",
            "simulate",
            "--poses",
            "0",
            "--seed",
            "1",
            "--output",
            "/tmp/x.csv",
        ],
        "",
    );
    assert_input_error(&o, &["--poses 0"]);
    let o = run(
        &[
            "calibrate",
            "simulate",
            "--poses",
            "10",
            "--seed",
            "1",
            "--install-error-deg",
            "30",
            "--output",
            "/tmp/x.csv",
        ],
        "",
    );
    assert_input_error(&o, &["could be aligned", "use smaller errors"]);
}

/// `axiscomp table …` without a service, or with bad arguments: one clear line, the exit code.
#[test]
fn table_commands_name_a_missing_service_and_bad_arguments() {
    let dir = TempDir::new("table-cli");
    let sock = dir.path("control.sock");
    let sock = sock.to_str().unwrap();
    for args in [
        vec!["table", "status", "--socket", sock],
        vec!["table", "list", "--socket", sock],
        vec!["table", "generate", "--run", "1", "--socket", sock],
        vec![
            "table",
            "publish",
            "--table",
            "1",
            "--confirm",
            "--socket",
            sock,
        ],
    ] {
        let o = run(&args, "");
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(1), "{args:?}: {err}");
        let last = err.lines().last().unwrap_or_default();
        assert!(
            last.contains("cannot connect to")
                && last.contains(sock)
                && last.contains("is the service running"),
            "{args:?}: {last}"
        );
    }
    // Without --confirm nothing is sent: an input error before connecting.
    let o = run(&["table", "publish", "--table", "3", "--socket", sock], "");
    assert_input_error(&o, &["--confirm", "table 3"]);
    // Missing or malformed arguments: clap's usage error, exit 2.
    for args in [
        vec!["table", "generate", "--socket", sock],
        vec!["table", "publish", "--table", "x", "--confirm"],
    ] {
        let o = run(&args, "");
        assert_eq!(o.status.code(), Some(2), "{args:?}: {}", stderr(&o));
    }
}

/// `axiscomp check` loads the CNC map `[plc]` names: a bad map, or a map that cannot serve
/// pull, is an input error naming the file and the key.
#[test]
fn check_validates_the_cnc_map() {
    let dir = TempDir::new("check-plc");
    let cfg = dir.write(
        "bad-map.toml",
        "[plc]\nmap = \"tests/fixtures/cnc-maps/overlap.toml\"\n",
    );
    let o = run(&["check", "--config", cfg.to_str().unwrap()], "");
    assert_input_error(&o, &["overlap.toml", "`header.points.address`"]);
    let cfg = dir.write(
        "pull-codesys.toml",
        "[plc]\nmap = \"plc-maps/cnc/codesys.toml\"\npull = true\n",
    );
    let o = run(&["check", "--config", cfg.to_str().unwrap()], "");
    assert_input_error(&o, &["codesys.toml", "handshake.plc_ready.address", "pull"]);
    let o = run(&["check", "--config", "configs/twin-service.toml"], "");
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stdout(&o).contains("PLC push: 127.0.0.1:5502 unit 1")
            && stdout(&o).contains("CNC: the twin at 127.0.0.1:5099 runs each part program (iso)")
            && stdout(&o).contains(
                "PLC check requests: read every second (check.request at 40011, answered at 40012)"
            ),
        "{}",
        stdout(&o)
    );
    // The generic map's check fields with push off: said, as the requests go unanswered.
    let cfg = dir.write("no-push.toml", "[plc]\nmap = \"builtin:generic\"\n");
    let o = run(&["check", "--config", cfg.to_str().unwrap()], "");
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stdout(&o).contains("PLC check requests: not read: the map has [check] but push is off"),
        "{}",
        stdout(&o)
    );
}

/// A reader that leaves early (`axiscomp decouple < readings.csv | head -1`) ends the command
/// as it ends `cat`: by SIGPIPE, with nothing on standard error, not with a panic's backtrace.
#[test]
fn a_closed_stdout_ends_a_filter_quietly() {
    use std::io::{BufRead, BufReader};
    use std::os::unix::process::ExitStatusExt;
    use std::process::Stdio;
    let mut child = crate::helpers::bin()
        .args(["decouple", "--simulated"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn axiscomp");
    // Far more output than a pipe buffers, so the command is still writing when we leave.
    let mut input = String::from("X1_um,Y1_um,X2_um,Y2_um,X3_um,Y3_um\n");
    for k in 0..20_000 {
        input.push_str(&format!("{k},0,0,0,0,0\n"));
    }
    let mut stdin = child.stdin.take().expect("stdin");
    let feeder = std::thread::spawn(move || {
        // The command may be gone before it has read everything: that is the point.
        let _ = std::io::Write::write_all(&mut stdin, input.as_bytes());
    });
    let mut out = BufReader::new(child.stdout.take().expect("stdout"));
    let mut header = String::new();
    out.read_line(&mut header).expect("the header line");
    assert!(header.starts_with("dx"), "{header}");
    drop(out);
    let o = child.wait_with_output().expect("wait axiscomp");
    let _ = feeder.join();
    let err = stderr(&o);
    assert!(!err.contains("panicked"), "{err}");
    assert_eq!(
        o.status.signal(),
        Some(libc::SIGPIPE),
        "{:?}: {err}",
        o.status
    );
}

/// Issue 26: a dwell the twin cannot capture in is refused before the calibration and the
/// follower's map (an hour of machine time), with the least dwell that works.
#[test]
fn the_demo_refuses_a_dwell_too_short_up_front() {
    let dir = TempDir::new("demo-dwell");
    let out = dir.path("out");
    let o = run(
        &[
            "demo",
            "--runs",
            "2",
            "--dwell-s",
            "1",
            "--length-mm",
            "600",
            "--targets",
            "7",
            "--seed",
            "7",
            "--out",
            out.to_str().expect("a UTF-8 path"),
        ],
        "",
    );
    assert_input_error(
        &o,
        &["a dwell of 1 s is too short to capture: use at least 1.45 s"],
    );
    assert!(!stdout(&o).contains("calibrate the head"), "{}", stdout(&o));
    assert!(!out.exists(), "nothing written");
}
