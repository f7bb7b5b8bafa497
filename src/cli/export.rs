//! `axiscomp export`: a stored run's compensation table for a controller. The controller's
//! settings come from `[comp.<controller>]`; the flags below override them. Thin over
//! `axiscomp::comp`.
//!
//! A run taken under compensation (issue 15: the tables active in the PLC are recorded with
//! the run) measured the residual only: the exported table is then the active table plus
//! that residual, on the active table's grid, and the file's header (where the format has
//! comments; JSON a `composition` key) and the command's output say so.

use super::InputError;
use super::run::{StoreArgs, open_store};
use anyhow::{Context, Result};
use axiscomp::comp::settings::{self, CompSettings};
use axiscomp::comp::{
    self, AxisMapping, CompTable, MachineAxis, PositioningMode, TableSpec, beckhoff, fanuc,
    heidenhain, linuxcnc, mitsubishi, siemens,
};
use axiscomp::evaluate::iso230_1::ReferenceLine;
use axiscomp::evaluate::{EvalOptions, evaluate_captures};
use axiscomp::store::RunId;
use clap::ValueEnum;
use std::path::{Path, PathBuf};

/// What the exports do not confirm from a public document (also in each file's header where
/// the format has comments).
pub const UNCONFIRMED: &str = "\
Unconfirmed from public documents (check on the control before use):
  siemens-cec  the sign (+e, as K3 states it for MSEC); M17 at the end (from the MSEC example)
  fanuc        the tape layout of 3605#0 (N03605A<a>P00000001); 3627's sign (taken as C = -e);
               the +-7 range of --family legacy and the -32768..32767 range of --family 30i
  heidenhain   the value sign (+e); whether BACKLASH holds e-down (backlash = \"negative\", the
               manual's words) or e-down - e-up (\"reversal\"); the TNC 640 row limit (256 is the
               TNC 407's); the TNC 4xx DATUM/SPACING lines and the .CMA layout
  linuxcnc     nothing beyond the file having no comments: nominals are joint positions in the
               joint's machine units (--units); add the file to every [JOINT_n] the axis drives
  beckhoff     the '#' comment lines and kw.ssfk.unit = 1 (from the manual's example)
  mitsubishi   the parameter numbers #4000-#4007 and #41xx for M800/M80/E70 (M700-era layout)";

#[derive(Clone, Copy, Debug, ValueEnum, PartialEq)]
pub enum Format {
    SiemensLec,
    SiemensCec,
    Fanuc,
    Heidenhain,
    LinuxcncType0,
    LinuxcncType1,
    Beckhoff,
    Mitsubishi,
    Csv,
    Json,
}

#[derive(Clone, Copy, Debug, ValueEnum, PartialEq)]
pub enum Table {
    Positioning,
    StraightnessX,
    StraightnessZ,
}

#[derive(clap::Args, Debug)]
#[command(after_help = UNCONFIRMED)]
pub struct ExportArgs {
    #[command(flatten)]
    pub store: StoreArgs,
    /// The controller's file format.
    #[arg(long, value_enum)]
    pub format: Format,
    /// Which table (the head's transverse x or vertical z straightness, or positioning).
    #[arg(long, value_enum, default_value_t = Table::Positioning)]
    pub table: Table,
    /// The machine axis the head measured along, X, Y or Z (default: the run's).
    #[arg(long)]
    pub axis: Option<String>,
    /// One table per direction instead of one with backlash.
    #[arg(long)]
    pub bidirectional: bool,
    /// Write the run's residual as the table when the tables the PLC applied while it ran
    /// are not recorded (a run not measured by the service). Loaded alone, a residual
    /// replaces the compensation it was measured under.
    #[arg(long)]
    pub residual_only: bool,
    /// The controller's name of the axis: Siemens machine axis (default X1/Y1/Z1, MD10000),
    /// Beckhoff logical axis name, Mitsubishi axis name, HEIDENHAIN column key.
    #[arg(long)]
    pub machine_axis: Option<String>,
    /// Machine position of the reference point (mm): the table is zero there (FANUC 3620,
    /// Siemens, TNC 4xx datum). Default: the run plan's reference.
    #[arg(long)]
    pub reference_mm: Option<f64>,
    /// LinuxCNC machine units: mm or inch.
    #[arg(long)]
    pub units: Option<String>,
    /// The controller's point limit (MD38000 / MD18342, FANUC points, rows, P-COMP-00059, …).
    #[arg(long)]
    pub max_points: Option<usize>,
    /// The control family or format: siemens 840d|828d, fanuc 0i|legacy|30i, heidenhain
    /// tnc640|tnc4xx, mitsubishi absolute|incremental.
    #[arg(long)]
    pub family: Option<String>,
    /// Spacing of the compensation points (mm); refused when the controller's limits cannot
    /// hold it. Default: the measured targets' mean spacing (power of two for TNC 4xx).
    #[arg(long)]
    pub step_mm: Option<f64>,
    /// The file to write (HEIDENHAIN: NAME.COM, with NAME.CMA beside it for tnc640).
    #[arg(long)]
    pub out: PathBuf,
}

/// The flags that override `[comp.*]`.
#[derive(Clone, Debug, Default)]
pub struct Overrides {
    pub machine_axis: Option<String>,
    pub units: Option<String>,
    pub max_points: Option<usize>,
    pub family: Option<String>,
    pub step_mm: Option<f64>,
}

/// What an export writes: the file, extra files beside it, and lines for the user.
pub struct Rendered {
    pub text: String,
    pub extra: Vec<(String, String)>,
    pub notes: Vec<String>,
}

/// A configured axis number, or (0) the axis's own: X 1, Y 2, Z 3.
fn or_axis_number<T: From<u8> + PartialEq>(configured: T, index: usize) -> T {
    if configured == T::from(0) {
        T::from(index as u8 + 1)
    } else {
        configured
    }
}

fn input(e: (String, String), flag: &str) -> anyhow::Error {
    InputError(format!("{flag} (or {}): {}", e.0, e.1)).into()
}

/// The file for `format` from `table` with the settings and flags.
pub fn render(
    table: &CompTable,
    format: Format,
    comp: &CompSettings,
    o: &Overrides,
    out: &Path,
) -> Result<Rendered> {
    let raw = &comp.raw;
    let letter = table.comp_axis.letter();
    let idx = table.comp_axis.index();
    let mut notes = Vec::new();
    let mut extra = Vec::new();
    let family = o.family.as_deref();
    let text = match format {
        Format::SiemensLec | Format::SiemensCec => {
            let control = match family {
                Some(f) => settings::siemens_control(f).map_err(|e| input(e, "--family"))?,
                None => comp.siemens_control,
            };
            let name = |cfg: &str, axis: MachineAxis| -> String {
                if cfg.is_empty() {
                    siemens::default_machine_axis(axis.letter())
                } else {
                    cfg.to_string()
                }
            };
            let machine_axis = o
                .machine_axis
                .clone()
                .unwrap_or_else(|| name(&raw.siemens.machine_axis, table.comp_axis));
            if format == Format::SiemensLec {
                siemens::lec(
                    table,
                    &siemens::LecOptions {
                        axis: machine_axis,
                        encoder: raw.siemens.encoder,
                        max_points: o.max_points.unwrap_or(raw.siemens.enc_comp_max_points),
                        step_mm: o.step_mm,
                        ends: comp.siemens_ends,
                    },
                )?
                .text
            } else {
                siemens::cec(
                    table,
                    &siemens::CecOptions {
                        table_index: raw.siemens.cec_table,
                        input_axis: name(&raw.siemens.input_axis, table.base_axis),
                        output_axis: machine_axis,
                        max_points: o.max_points.unwrap_or(raw.siemens.cec_max_points),
                        step_mm: o.step_mm,
                        ends: comp.siemens_ends,
                        control,
                    },
                )?
                .text
            }
        }
        Format::Fanuc => {
            let range = match family {
                Some(f) => settings::fanuc_family(f).map_err(|e| input(e, "--family"))?,
                None => comp.fanuc_range,
            };
            let f = &raw.fanuc;
            let x = fanuc::pitch(
                table,
                &fanuc::PitchOptions {
                    axis_number: or_axis_number(f.axis_number, idx),
                    reference_number: f.reference_number,
                    max_number: f.max_number,
                    max_points: o.max_points.unwrap_or(f.max_points),
                    input_increment_mm: f.input_increment_mm,
                    detection_unit_mm: f.detection_unit_mm,
                    magnification: f.magnification,
                    range,
                    min_interval_mm: 0.0,
                    max_feed_mm_min: Some(f.max_feed_mm_min),
                    step_mm: o.step_mm,
                    negative_start: f.negative_start,
                },
            )?;
            notes.push(format!(
                "reference position (parameter 3620's point) at {} mm",
                table.reference_mm
            ));
            x.text
        }
        Format::Heidenhain => {
            let fam = match family {
                Some(f) => settings::heidenhain_family(f).map_err(|e| input(e, "--family"))?,
                None => comp.heidenhain_family,
            };
            let h = &raw.heidenhain;
            let key = o
                .machine_axis
                .clone()
                .or_else(|| (!h.axis_key.is_empty()).then(|| h.axis_key.clone()));
            let file_name = out
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_else(|| "AXISCOMP.COM".into());
            let x = heidenhain::com(
                table,
                &heidenhain::ComOptions {
                    file_name: file_name.clone(),
                    axis_key: key.clone(),
                    max_points: o.max_points.unwrap_or(h.max_points),
                    step_mm: o.step_mm,
                    family: fam,
                    datum_mm: h.datum_mm,
                    backlash: comp.heidenhain_backlash,
                },
            )?;
            if fam == heidenhain::Family::Tnc640 {
                let stem = file_name
                    .rsplit_once('.')
                    .map(|(s, _)| s)
                    .unwrap_or(&file_name);
                extra.push((
                    format!("{stem}.CMA"),
                    heidenhain::cma(table, &file_name, key.as_deref()),
                ));
            }
            x.text
        }
        Format::LinuxcncType0 | Format::LinuxcncType1 => {
            let units = match &o.units {
                Some(u) => settings::linuxcnc_units(u).map_err(|e| input(e, "--units"))?,
                None => comp.linuxcnc_units,
            };
            let (file_type, ty) = if format == Format::LinuxcncType0 {
                (linuxcnc::CompFileType::Type0, 0)
            } else {
                (linuxcnc::CompFileType::Type1, 1)
            };
            let x = linuxcnc::comp_file(
                table,
                &linuxcnc::CompFileOptions {
                    file_type,
                    units,
                    max_points: o.max_points.unwrap_or(raw.linuxcnc.max_points),
                    step_mm: o.step_mm,
                },
            )?;
            let joints = if raw.linuxcnc.joints.is_empty() {
                vec![idx as u8]
            } else {
                raw.linuxcnc.joints.clone()
            };
            notes.push(format!(
                "in {}: nominals are joint positions; LINEAR_UNITS must be {}",
                units.name(),
                units.name()
            ));
            for j in joints {
                notes.push(format!(
                    "[JOINT_{j}] COMP_FILE = {}  COMP_FILE_TYPE = {ty}",
                    out.display()
                ));
            }
            x.text
        }
        Format::Beckhoff => {
            let b = &raw.beckhoff;
            beckhoff::ssfk(
                table,
                &beckhoff::SsfkOptions {
                    axis_number: or_axis_number(b.axis_number, idx),
                    axis_name: o.machine_axis.clone().unwrap_or_else(|| {
                        if b.axis_name.is_empty() {
                            letter.to_string()
                        } else {
                            b.axis_name.clone()
                        }
                    }),
                    max_points: o.max_points.unwrap_or(b.max_points),
                    step_mm: o.step_mm,
                },
            )?
            .text
        }
        Format::Mitsubishi => {
            let m = &raw.mitsubishi;
            mitsubishi::mec(
                table,
                &mitsubishi::MecOptions {
                    axis_name: o.machine_axis.clone().unwrap_or_else(|| letter.to_string()),
                    mode: match family {
                        Some(f) => {
                            settings::mitsubishi_mode(f).map_err(|e| input(e, "--family"))?
                        }
                        None => comp.mitsubishi_mode,
                    },
                    output_unit_mm: m.output_unit_mm,
                    scale: m.scale,
                    first_number: m.first_number,
                    max_points: o.max_points.unwrap_or(m.max_points),
                    step_mm: o.step_mm,
                },
            )?
            .text
        }
        Format::Csv => comp::neutral::csv(table),
        Format::Json => comp::neutral::json(table)?,
    };
    Ok(Rendered { text, extra, notes })
}

/// `axiscomp export --run ID --format FORMAT --out FILE`.
pub fn run(a: ExportArgs) -> Result<()> {
    let settings = super::service::settings(a.store.config.as_deref())?;
    let store = open_store(&a.store)?;
    let id = RunId(a.store.run);
    // Finished, no flag open, and what the PLC applied while it ran known (issue 24).
    let during =
        axiscomp::service::composition::usable(&store, id, a.residual_only).map_err(InputError)?;
    let rec = store.run(id)?;
    let captures = store.captures(id)?;
    let eval = evaluate_captures(&captures, &EvalOptions::default())?;
    let axis_name = a.axis.clone().unwrap_or(rec.axis.clone());
    let axis = MachineAxis::from_letter(&axis_name)
        .ok_or_else(|| InputError(format!("--axis {axis_name}: use X, Y or Z")))?;
    let plan: Option<axiscomp::run::Plan> = serde_json::from_value(rec.plan.clone()).ok();
    let spec = TableSpec {
        mapping: AxisMapping::standard(axis),
        reference_mm: a
            .reference_mm
            .or(plan.map(|p| p.reference_mm))
            .unwrap_or(0.0),
        positioning: if a.bidirectional {
            PositioningMode::Bidirectional
        } else {
            PositioningMode::Unidirectional
        },
        straightness_line: ReferenceLine::LeastSquares,
        functional_point_mm: None,
    };
    let set = comp::build_tables(&eval, &spec)?;
    let table = match a.table {
        Table::Positioning => &set.positioning,
        Table::StraightnessX => set
            .straightness
            .first()
            .ok_or_else(|| InputError("no straightness table".into()))?,
        Table::StraightnessZ => set
            .straightness
            .get(1)
            .ok_or_else(|| InputError("no vertical straightness table".into()))?,
    };
    let (composed, composition) = compose_with_active(&store, id, during.as_ref(), table)?;
    let table = composed.as_ref().unwrap_or(table);
    let o = Overrides {
        machine_axis: a.machine_axis.clone(),
        units: a.units.clone(),
        max_points: a.max_points,
        family: a.family.clone(),
        step_mm: a.step_mm,
    };
    let r = render(table, a.format, &settings.comp, &o, &a.out).map_err(|e| match e
        .downcast::<comp::CompError>()
    {
        Ok(c) => InputError(c.to_string()).into(),
        Err(e) => e,
    })?;
    let text = match &composition {
        Some(line) => mark_composed(&r.text, a.format, line),
        None => r.text.clone(),
    };
    std::fs::write(&a.out, &text).with_context(|| format!("writing {}", a.out.display()))?;
    let name = a
        .format
        .to_possible_value()
        .map(|v| v.get_name().to_string())
        .unwrap_or_default();
    eprintln!("wrote {} ({name} table {})", a.out.display(), table.name);
    for (file, text) in &r.extra {
        let p = a.out.with_file_name(file);
        std::fs::write(&p, text).with_context(|| format!("writing {}", p.display()))?;
        eprintln!("wrote {}", p.display());
    }
    if let Some(line) = &composition {
        eprintln!("{line}");
    }
    for n in &r.notes {
        eprintln!("{n}");
    }
    Ok(())
}

/// When run `id` ran with a table of `table`'s kind active: that table plus `table` (the
/// residual), and the line that says so.
fn compose_with_active(
    store: &axiscomp::store::Store,
    id: RunId,
    during: Option<&axiscomp::store::RunTables>,
    table: &CompTable,
) -> Result<(Option<CompTable>, Option<String>)> {
    use axiscomp::service::composition::grid_table;
    use axiscomp::service::stored::Base;
    use axiscomp::service::stored::StoredTable;
    let Some(a) = during.and_then(|d| d.find(table.kind.name(), table.comp_axis.letter())) else {
        return Ok((None, None));
    };
    let cannot = |why: String| {
        anyhow::anyhow!(
            "run {id} was measured while the PLC applied {} {} sequence {}: it saw only the residual, and {} cannot be composed with that table ({why})",
            a.kind,
            a.axis,
            a.sequence,
            table.name
        )
    };
    let base_id = a
        .table
        .ok_or_else(|| cannot("it is not in the store".into()))?;
    let base = StoredTable::from_record(&store.table(base_id)?).map_err(cannot)?;
    let composed = comp::table::compose(&grid_table(&base).map_err(cannot)?, table)
        .map_err(|e| cannot(e.to_string()))?;
    let line = format!(
        "composed: {}",
        Base {
            active: a.clone(),
            run_id: id.0,
        }
        .describe()
    );
    Ok((Some(composed), Some(line)))
}

/// `text` with `line` in its header: after the first comment line (`;` or `#`), as a JSON
/// key, or unchanged where the format has no comments.
fn mark_composed(text: &str, format: Format, line: &str) -> String {
    if format == Format::Json {
        let key = format!(
            "  \"composition\": {},\n",
            serde_json::to_string(line).unwrap_or_default()
        );
        return match text.find("{\n") {
            Some(i) => format!("{}{key}{}", &text[..i + 2], &text[i + 2..]),
            None => text.to_string(),
        };
    }
    let mut out = String::with_capacity(text.len() + line.len() + 4);
    let mut done = false;
    for l in text.split_inclusive('\n') {
        out.push_str(l);
        if !done && let Some(marker) = [";", "#"].into_iter().find(|m| l.starts_with(m)) {
            out.push_str(&format!("{marker} {line}\n"));
            done = true;
        }
    }
    out
}
