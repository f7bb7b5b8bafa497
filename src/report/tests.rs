use super::xml_check::{self, Doc};
use super::*;
use crate::run::Direction;
use std::sync::atomic::{AtomicUsize, Ordering};

/// A fresh directory, removed on drop.
struct TempDir(PathBuf);

impl TempDir {
    fn new(name: &str) -> TempDir {
        static N: AtomicUsize = AtomicUsize::new(0);
        let p = std::env::temp_dir().join(format!(
            "axiscomp-report-{}-{}-{name}",
            std::process::id(),
            N.fetch_add(1, Ordering::Relaxed)
        ));
        let _ = std::fs::remove_dir_all(&p);
        std::fs::create_dir_all(&p).unwrap();
        TempDir(p)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

const TARGETS: usize = 11;

/// A series of `dof` in user units (µm or arcsec), converted to internal as the input wants.
fn series(dof: Dof, direction: Direction, shift: f64, with_u: bool) -> Series {
    let to_internal = |v: f64| v / dof.to_user(1.0);
    let positions_mm: Vec<f64> = (0..TARGETS).map(|i| 50.0 * i as f64).collect();
    let k = dof.index() as f64 + 1.0;
    let user_mean: Vec<f64> = positions_mm
        .iter()
        .map(|&x| k * (x / 120.0).sin() + 0.004 * x + shift)
        .collect();
    let user_s: Vec<f64> = (0..TARGETS).map(|i| 0.2 + 0.03 * i as f64).collect();
    Series {
        direction,
        // Deliberately not sorted: the plots and tables sort.
        positions_mm: positions_mm.iter().rev().copied().collect(),
        mean: user_mean.iter().rev().map(|&v| to_internal(v)).collect(),
        s: user_s.iter().rev().map(|&v| to_internal(v)).collect(),
        n: vec![5; TARGETS],
        u: with_u.then(|| vec![to_internal(0.1); TARGETS]),
    }
}

fn result(dof: Dof) -> DofResult {
    DofResult {
        dof,
        series: vec![
            series(dof, Direction::Up, 0.0, dof == Dof::Dy),
            series(dof, Direction::Down, -1.5, dof == Dof::Dy),
        ],
        figures: vec![
            Figure {
                name: "E".into(),
                value: 7.25,
                unit: dof.unit().into(),
            },
            Figure {
                name: "B".into(),
                value: 1.5,
                unit: dof.unit().into(),
            },
            Figure {
                name: "A".into(),
                value: -0.0004,
                unit: dof.unit().into(),
            },
        ],
        budget: (dof == Dof::Dy).then(budget_table),
    }
}

/// A budget of two terms for dy, its expanded U stated at the up series' first position only.
fn budget_table() -> BudgetTable {
    BudgetTable {
        k: 2.0,
        terms: vec![
            BudgetTerm {
                name: "PSD noise".into(),
                formula: "√(Σ sd²/frames)/n".into(),
                source: "frames".into(),
                largest: 0.3,
            },
            BudgetTerm {
                name: "follower map".into(),
                formula: "S·u".into(),
                source: "specification ±4 µm".into(),
                largest: 0.4,
            },
        ],
        largest_combined: 0.5,
        largest_expanded: 1.0,
        points: vec![BudgetPoint {
            position_mm: 0.0,
            direction: Direction::Up,
            terms: vec![0.3, 0.4],
            combined: 0.5,
            expanded: 1.0,
        }],
    }
}

fn sample() -> RunReport {
    RunReport {
        meta: RunMeta {
            run_id: 12,
            axis: "Y".into(),
            state: "finished".into(),
            created_us: 1_740_823_200_000_000,
            updated_us: 1_740_826_800_500_000,
            plan: vec![
                ("targets".into(), "11, 0 to 500 mm".into()),
                ("runs".into(), "5 bidirectional".into()),
            ],
            config: vec![("capture".into(), "stability, 2 s at rest".into())],
            notes: "Cover <removed> & \"way\" | cleaned\n*second* line".into(),
        },
        dofs: Dof::ALL.iter().map(|&d| result(d)).collect(),
        comparisons: vec![Comparison {
            dof: Dof::Dy,
            before_label: "before".into(),
            before: vec![
                series(Dof::Dy, Direction::Up, 4.0, false),
                series(Dof::Dy, Direction::Down, 2.0, false),
            ],
            after_label: "after".into(),
            after: vec![
                series(Dof::Dy, Direction::Up, 0.0, false),
                series(Dof::Dy, Direction::Down, -0.5, false),
            ],
        }],
        environment: vec![
            EnvSample {
                unix_us: 1_740_823_300_000_000,
                material_c: Some(20.4),
                air_c: Some(21.0),
            },
            EnvSample {
                unix_us: 1_740_826_000_000_000,
                material_c: Some(20.9),
                air_c: None,
            },
        ],
    }
}

/// The palette's blue and red (`doc::PALETTE` 0 and 3): ↑ and ↓.
const UP_HEX: &str = "#1f5ab4";
const DOWN_HEX: &str = "#be2828";

fn svg_doc(svg: &str) -> Doc {
    let doc = xml_check::parse(svg).unwrap_or_else(|e| panic!("SVG is not well-formed: {e}"));
    assert_eq!(doc.root, "svg");
    doc
}

fn centre(e: &xml_check::Element) -> (f64, f64) {
    (
        e.attr("cx").unwrap().parse().unwrap(),
        e.attr("cy").unwrap().parse().unwrap(),
    )
}

#[test]
fn dof_svg_has_one_marker_per_point_and_a_band_per_direction() {
    let r = result(Dof::Dy);
    let svg = plot::dof_svg(&r).unwrap();
    let doc = svg_doc(&svg);
    // A marker per point, and one beside each legend entry (drawn last).
    assert_eq!(doc.count("circle"), 2 * TARGETS + 2);
    assert_eq!(doc.count("polygon"), 2, "one ±2s band per direction");
    assert!(doc.has_text("dy — positioning"));
    assert!(doc.has_text("position (mm)"));
    assert!(doc.has_text("dy (µm)"));
    assert!(doc.has_text("↑ mean ±2s") && doc.has_text("↓ mean ±2s"));

    // The ↑ markers are the ↑ series, in position order, higher means higher up.
    let up: Vec<(f64, f64)> = doc
        .named("circle")
        .filter(|c| c.attr("fill") == Some(UP_HEX))
        .map(centre)
        .take(TARGETS)
        .collect();
    assert_eq!(up.len(), TARGETS);
    assert!(
        up.windows(2).all(|w| w[0].0 < w[1].0),
        "x grows with position"
    );
    let s = &r.series[0];
    let mut means: Vec<(f64, f64)> = s
        .positions_mm
        .iter()
        .copied()
        .zip(s.mean.iter().copied())
        .collect();
    means.sort_by(|a, b| a.0.total_cmp(&b.0));
    for i in 0..TARGETS {
        for j in 0..TARGETS {
            if means[i].1 > means[j].1 + 1e-4 {
                assert!(up[i].1 <= up[j].1, "point {i} is above point {j}");
            }
        }
    }
    let down = doc
        .named("circle")
        .filter(|c| c.attr("fill") == Some(DOWN_HEX))
        .count();
    assert_eq!(down, TARGETS + 1);
}

#[test]
fn angular_plots_are_labelled_in_arcsec() {
    let doc = svg_doc(&plot::dof_svg(&result(Dof::Ey)).unwrap());
    assert!(doc.has_text("ey — roll"));
    assert!(doc.has_text("ey (arcsec)"));
}

#[test]
fn six_svg_has_all_six_charts() {
    let report = sample();
    let mut dofs = report.dofs.clone();
    dofs.retain(|d| d.dof != Dof::Ez);
    let doc = svg_doc(&plot::six_svg(&dofs, "Run 12, axis Y: the six errors").unwrap());
    assert_eq!(doc.count("circle"), 5 * 2 * (TARGETS + 1));
    assert_eq!(doc.count("polygon"), 5 * 2);
    assert!(doc.has_text("Run 12, axis Y: the six errors"));
    for d in Dof::ALL {
        assert!(doc.has_text(&d.title()), "{}", d.title());
        assert!(doc.has_text(&format!("{} ({})", d.name(), d.unit())));
    }
    assert!(doc.has_text("no data"), "the missing yaw says so");
}

#[test]
fn comparison_svg_draws_both_sets() {
    let c = &sample().comparisons[0];
    let doc = svg_doc(&plot::comparison_svg(c).unwrap());
    assert_eq!(doc.count("circle"), 4 * (TARGETS + 1));
    assert_eq!(doc.count("polygon"), 4);
    let hollow = doc
        .named("circle")
        .filter(|e| e.attr("fill") == Some("none"))
        .count();
    assert_eq!(
        hollow,
        2 * (TARGETS + 1),
        "the before set has hollow markers"
    );
    assert!(doc.has_text("dy — positioning: before vs after"));
    for label in ["before ↑", "before ↓", "after ↑", "after ↓"] {
        assert!(doc.has_text(label), "{label}");
    }
}

fn png_size(path: &Path) -> (u32, u32) {
    let bytes = std::fs::read(path).unwrap();
    assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n", "PNG signature");
    assert_eq!(&bytes[12..16], b"IHDR");
    let be = |i: usize| u32::from_be_bytes([bytes[i], bytes[i + 1], bytes[i + 2], bytes[i + 3]]);
    (be(16), be(20))
}

#[test]
fn pngs_have_the_signature_and_size() {
    let dir = TempDir::new("png");
    let r = sample();
    let one = dir.0.join("dy.png");
    plot::dof_png(&r.dofs[1], &one).unwrap();
    // Each PNG is its SVG's size at the PNG scale (the same drawing).
    let svg_size = |svg: &str| {
        let doc = svg_doc(svg);
        let root = doc.named("svg").next().unwrap();
        let px = |a: &str| (root.attr(a).unwrap().parse::<f64>().unwrap() * plot::PNG_SCALE) as u32;
        (px("width"), px("height"))
    };
    assert_eq!(
        png_size(&one),
        svg_size(&plot::dof_svg(&r.dofs[1]).unwrap())
    );
    assert_eq!(
        png_size(&one).0,
        1040,
        "500 points and a margin of 10, at 2 pixels a point"
    );
    let six = dir.0.join("six.png");
    plot::six_png(&r.dofs, "six", &six).unwrap();
    assert_eq!(
        png_size(&six),
        svg_size(&plot::six_svg(&r.dofs, "six").unwrap())
    );
    let cmp = dir.0.join("compare.png");
    plot::comparison_png(&r.comparisons[0], &cmp).unwrap();
    assert_eq!(
        png_size(&cmp),
        svg_size(&plot::comparison_svg(&r.comparisons[0]).unwrap())
    );
    // Not blank: a real plot has many distinct bytes after compression.
    assert!(std::fs::metadata(&one).unwrap().len() > 10_000);
}

#[test]
fn html_is_well_formed_self_contained_and_escaped() {
    let r = sample();
    let svgs = html::Svgs {
        six: Some(plot::six_svg(&r.dofs, &text::six_title(&r.meta)).unwrap()),
        dofs: r.dofs.iter().map(|d| plot::dof_svg(d).unwrap()).collect(),
        comparisons: r
            .comparisons
            .iter()
            .map(|c| plot::comparison_svg(c).unwrap())
            .collect(),
    };
    let page = html::render(&r, &svgs);
    assert!(page.starts_with("<!DOCTYPE html>"));
    let doc = xml_check::parse(&page).unwrap_or_else(|e| panic!("HTML is not balanced: {e}"));
    assert_eq!(doc.root, "html");
    assert_eq!(doc.count("svg"), 1 + 6 + 1);
    assert_eq!(doc.count("h2"), 4 + 1 + 6 + 1 + 1);
    // The run's tables, figures and points per DOF, the environment, and dy's budget with
    // its per-point table.
    assert_eq!(doc.count("table"), 3 + 6 * 2 + 1 + 2);
    assert_eq!(doc.count("h4"), 1);
    // No scripts, no external resources.
    assert!(!page.to_ascii_lowercase().contains("<script"));
    for banned in ["script", "link", "img", "iframe", "object", "embed"] {
        assert_eq!(doc.count(banned), 0, "{banned}");
    }
    assert!(
        doc.elements
            .iter()
            .all(|e| e.attr("src").is_none() && e.attr("href").is_none())
    );
    // The notes are text, not markup.
    assert!(page.contains("Cover &lt;removed&gt; &amp; &quot;way&quot; | cleaned"));
    assert!(!page.contains("<removed>"));
    // Figures and points in user units.
    assert!(doc.has_text("7.250"));
    assert!(doc.has_text("Mean (µm)") && doc.has_text("Mean (arcsec)"));
    assert!(doc.has_text("2025-03-01T10:00:00Z"));
}

#[test]
fn markdown_report_golden() {
    insta::assert_snapshot!(markdown::render(&sample()));
}

#[test]
fn write_run_report_writes_every_file_it_references() {
    let dir = TempDir::new("write");
    let out = dir.0.join("run-12");
    let files = write_run_report(&out, &sample()).unwrap();
    let names: Vec<String> = files
        .iter()
        .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
        .collect();
    let mut expected = vec!["six.svg".to_string()];
    expected.extend(Dof::ALL.iter().map(|d| format!("{}.svg", d.name())));
    expected.push("compare-dy.svg".into());
    expected.push("report.html".into());
    expected.push("report.md".into());
    expected.push("six.png".into());
    expected.extend(Dof::ALL.iter().map(|d| format!("{}.png", d.name())));
    expected.push("compare-dy.png".into());
    assert_eq!(names, expected);
    for f in &files {
        assert!(f.starts_with(&out));
        assert!(std::fs::metadata(f).unwrap().len() > 0, "{}", f.display());
    }
    // Every image the Markdown references is beside it.
    let md = std::fs::read_to_string(out.join("report.md")).unwrap();
    let refs: Vec<&str> = md
        .match_indices("](")
        .map(|(i, _)| {
            let rest = &md[i + 2..];
            &rest[..rest.find(')').unwrap()]
        })
        .collect();
    assert_eq!(refs.len(), 1 + 6 + 1);
    for r in refs {
        assert!(r.ends_with(".png"));
        assert!(png_size(&out.join(r)).0 > 0);
    }
    // The SVG files are the ones inlined in the HTML.
    let page = std::fs::read_to_string(out.join("report.html")).unwrap();
    let dy = std::fs::read_to_string(out.join("dy.svg")).unwrap();
    assert!(page.contains(dy.trim()));
}

#[test]
fn bad_input_is_refused_with_what_is_wrong() {
    let mut r = sample();
    r.dofs[2].series[1].s.pop();
    let err = write_run_report(Path::new("/nonexistent/never"), &r).unwrap_err();
    assert!(matches!(err, ReportError::Input { .. }));
    assert!(err.to_string().contains("dz ↓ series"), "{err}");

    let mut r = sample();
    r.dofs[0].series[0].mean[3] = f64::NAN;
    assert!(plot::dof_svg(&r.dofs[0]).is_err());
    assert!(matches!(r.validate(), Err(ReportError::Input { .. })));

    let mut r = sample();
    r.dofs[0].series[0].s[0] = -1.0;
    assert!(r.validate().is_err());

    let mut r = sample();
    r.dofs.push(result(Dof::Dx));
    let err = r.validate().unwrap_err();
    assert!(err.to_string().contains("twice"), "{err}");

    let mut r = sample();
    r.dofs[0].series[0] = Series {
        direction: Direction::Up,
        positions_mm: vec![],
        mean: vec![],
        s: vec![],
        n: vec![],
        u: None,
    };
    assert!(r.validate().is_err());
}

#[test]
fn a_result_without_series_is_drawn_as_no_data() {
    let r = DofResult {
        dof: Dof::Ex,
        series: vec![],
        figures: vec![],
        budget: None,
    };
    let doc = svg_doc(&plot::dof_svg(&r).unwrap());
    assert!(doc.has_text("no data"));
    assert_eq!(doc.count("circle"), 0);
}

#[test]
fn meta_from_a_stored_run() {
    let rec = crate::store::RunRecord {
        id: crate::store::RunId(3),
        created_us: 0,
        updated_us: 1_000_000,
        state: crate::store::RunState::Running,
        axis: "X".into(),
        plan: serde_json::json!({"runs": 5}),
        config: serde_json::json!(null),
        calibration: None,
        notes: "n".into(),
    };
    let m = RunMeta::from_record(&rec);
    assert_eq!(m.run_id, 3);
    assert_eq!(m.state, "running");
    assert_eq!(m.plan, [("runs".to_string(), "5".to_string())]);
    assert!(m.config.is_empty());
    assert_eq!(text::date(m.updated_us), "1970-01-01T00:00:01Z");
}

/// Writes the sample report to `target/report-example/` for a person to look at:
/// `cargo test --lib report::tests::example_report -- --ignored`.
#[test]
#[ignore]
fn example_report() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("target/report-example");
    let files = write_run_report(&dir, &sample()).unwrap();
    for f in files {
        println!("{}", f.display());
    }
}
