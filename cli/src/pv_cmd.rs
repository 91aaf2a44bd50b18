//! `lungdyn pv presets | simulate | fit`: the pressure–volume relation on the command line.

use std::path::PathBuf;

use lung_bake::pv::curve::{read_curve, VolumeUnit};
use lung_bake::pv::fit::{fit_curve, model_at, CurveFit, FitOptions, PhaseFit};
use lung_model::pv::files::{PvConstantsFile, CONSTANTS_FORMAT};
use lung_model::pv::{control_curve, phase_curve, preset, Boundary, PhaseConstants, PRESET_NAMES};
use serde::Serialize;

use crate::plot::{self, Panel, Series, DATA, EXHALE, INHALE};

/// Options of `lungdyn pv simulate`.
#[derive(Debug, Clone, clap::Args)]
pub struct SimulateArgs {
    /// Preset (Table 5.1 row; `lungdyn pv presets` lists them).
    #[arg(long, default_value = lung_model::pv::DEFAULT_PRESET)]
    pub preset: String,
    /// Or a constants file written by `lungdyn pv fit` (replaces the preset).
    #[arg(long, conflicts_with = "preset")]
    pub constants: Option<PathBuf>,
    /// Override q (both phases).
    #[arg(long)]
    pub q: Option<f64>,
    /// Override c (both phases).
    #[arg(long)]
    pub c: Option<f64>,
    /// Override T_ext (both phases): hysteresis, 0 for normal breathing.
    #[arg(long)]
    pub t_ext: Option<f64>,
    /// Override the inhalation control constants, comma-separated (N odd ≥ 3).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub chi_inhale: Option<Vec<f64>>,
    /// Override the exhalation control constants, comma-separated.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub chi_exhale: Option<Vec<f64>>,
    /// Override FRC, ml.
    #[arg(long)]
    pub frc: Option<f64>,
    /// Override TV, ml.
    #[arg(long)]
    pub tv: Option<f64>,
    /// Override the top pressure, cmH2O.
    #[arg(long)]
    pub tp: Option<f64>,
    /// Samples per phase in the CSV.
    #[arg(long, default_value_t = 100)]
    pub samples: usize,
    /// Output CSV (phase, t, pressure_cmh2o, volume_ml, damping).
    #[arg(long)]
    pub out: PathBuf,
    /// Also plot the loop and the damping functions (PNG; an SVG is written beside it).
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Print a JSON summary on stdout.
    #[arg(long)]
    pub json: bool,
}

/// Options of `lungdyn pv fit`.
#[derive(Debug, Clone, clap::Args)]
pub struct FitArgs {
    /// Measured curve CSV with a header row: pressure and volume columns, found by name
    /// ("pressure"/"pes"/"paw"/"ptp", "volume"/"vol"), else the first two numeric columns;
    /// optional `phase` column (inhale/exhale), else split at the sample of maximum volume. Units
    /// come from the header where it names them (pressure_kPa, Paw (mmHg), pressure_Pa, hPa, mbar,
    /// cmH2O; volume_ml, volume (L), dL) and are converted to cmH2O and ml and reported; an
    /// unnamed unit is cmH2O and ml. Every value is checked against human ranges.
    #[arg(long)]
    pub input: PathBuf,
    /// Unit of the volume column when the header does not name one (a header that names another
    /// unit is an error).
    #[arg(long, value_parser = ["ml", "l"])]
    pub volume_unit: Option<String>,
    /// The volume column holds changes above FRC: add this FRC (ml) to every volume.
    #[arg(long, value_name = "ML")]
    pub frc: Option<f64>,
    /// The volume column holds changes above FRC (as ventilators and compliance curves give them;
    /// also read so when its header says `delta` or `above_frc`): FRC is --frc, else Table 5.2's
    /// 2400 ml (said so).
    #[arg(long)]
    pub relative: bool,
    /// Input size limit and special files.
    #[command(flatten)]
    pub input_args: crate::input_args::InputArgs,
    /// Fix q (else the fit chooses it).
    #[arg(long)]
    pub q: Option<f64>,
    /// Fix c (else the fit chooses it).
    #[arg(long)]
    pub c: Option<f64>,
    /// Hysteresis constant T_ext held during the fit.
    #[arg(long, default_value_t = 0.0)]
    pub t_ext: f64,
    /// Write the constants as TOML (usable from a scene: `[pv] constants = "FILE"`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Plot data and fit (PNG; an SVG is written beside it).
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Print one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

/// `lungdyn pv` subcommands.
#[derive(Debug, Clone, clap::Subcommand)]
pub enum PvCommand {
    /// List the presets of Table 5.1 (with Table 5.2 boundary values).
    Presets,
    /// Simulate one breathing cycle: CSV of the PV loop and damping curves, optional plots.
    Simulate(SimulateArgs),
    /// Fit a measured PV loop: constants per phase, RMS error, condition number, boundary values.
    Fit(FitArgs),
    /// A ventilator recording cut into breaths: per breath tidal volume, rate, I:E, PIP, PEEP,
    /// compliance and resistance (equation of motion), a class with its reason, the PV fit.
    Recording(crate::pv_recording::RecordingArgs),
}

/// Run a `lungdyn pv` subcommand.
pub fn run(cmd: &PvCommand) -> anyhow::Result<()> {
    match cmd {
        PvCommand::Presets => presets(),
        PvCommand::Simulate(a) => simulate(a),
        PvCommand::Fit(a) => fit(a),
        PvCommand::Recording(a) => crate::pv_recording::run(a),
    }
}

fn presets() -> anyhow::Result<()> {
    for name in PRESET_NAMES {
        let p = preset(name)?;
        let fmt = |k: &PhaseConstants| {
            k.chi
                .iter()
                .map(|c| c.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        };
        println!("{name:<30} {}", p.source);
        println!(
            "{:<30} inhale  chi = [{}], q = {}",
            "",
            fmt(&p.inhale),
            p.inhale.q
        );
        if p.exhale != p.inhale {
            println!(
                "{:<30} exhale  chi = [{}], q = {}",
                "",
                fmt(&p.exhale),
                p.exhale.q
            );
        }
        println!(
            "{:<30} FRC {} ml, TV {} ml, RP {} cmH2O, TP {} cmH2O",
            "", p.boundary.frc_ml, p.boundary.tv_ml, p.boundary.rp_cmh2o, p.boundary.tp_cmh2o
        );
    }
    Ok(())
}

/// The constants `simulate` uses after overrides.
pub fn simulate_constants(
    a: &SimulateArgs,
) -> anyhow::Result<(PhaseConstants, PhaseConstants, Boundary, String)> {
    let (mut inhale, mut exhale, mut boundary, name) = match &a.constants {
        Some(path) => {
            let f = PvConstantsFile::load(path)?;
            (f.inhale, f.exhale, f.boundary, path.display().to_string())
        }
        None => {
            let p = preset(&a.preset)?;
            (p.inhale, p.exhale, p.boundary, p.name.to_string())
        }
    };
    for k in [&mut inhale, &mut exhale] {
        if let Some(q) = a.q {
            k.q = q;
        }
        if let Some(c) = a.c {
            k.c = c;
        }
        if let Some(t) = a.t_ext {
            k.t_ext = t;
        }
    }
    if let Some(chi) = &a.chi_inhale {
        inhale.chi = chi.clone();
    }
    if let Some(chi) = &a.chi_exhale {
        exhale.chi = chi.clone();
    }
    // Every constant in its documented range before any work, naming where a bad one came from.
    for (phase, k, chi_flag) in [
        (
            "inhalation",
            &inhale,
            a.chi_inhale.is_some().then_some("--chi-inhale"),
        ),
        (
            "exhalation",
            &exhale,
            a.chi_exhale.is_some().then_some("--chi-exhale"),
        ),
    ] {
        let flags: Vec<&str> = [
            chi_flag,
            a.q.map(|_| "--q"),
            a.c.map(|_| "--c"),
            a.t_ext.map(|_| "--t-ext"),
        ]
        .into_iter()
        .flatten()
        .collect();
        k.validate().map_err(|e| {
            let from = if flags.is_empty() {
                name.clone()
            } else {
                format!("{} over {name}", flags.join(", "))
            };
            anyhow::anyhow!("{phase} constants ({from}): {e}")
        })?;
    }
    boundary.frc_ml = a.frc.unwrap_or(boundary.frc_ml);
    boundary.tv_ml = a.tv.unwrap_or(boundary.tv_ml);
    boundary.tp_cmh2o = a.tp.unwrap_or(boundary.tp_cmh2o);
    boundary
        .check_plausible()
        .map_err(|e| anyhow::anyhow!("--frc/--tv/--tp: {e}"))?;
    Ok((inhale, exhale, boundary, name))
}

#[derive(Serialize)]
struct SimulateSummary {
    csv: String,
    plots: Vec<String>,
    rows: usize,
}

/// Check `--out` (any name) and `--plot` (a .png, with its .svg beside it) before any work.
fn check_outputs(
    out: Option<&std::path::Path>,
    plot: Option<&std::path::Path>,
) -> anyhow::Result<()> {
    use crate::outputs::{check_all, Output};
    let mut outputs = Vec::new();
    if let Some(path) = out {
        outputs.push(Output {
            flag: "--out",
            path,
            extensions: &[],
        });
    }
    let mut also = Vec::new();
    if let Some(path) = plot {
        outputs.push(Output {
            flag: "--plot",
            path,
            extensions: &["png"],
        });
        also.push(("--plot", plot::svg_of(path)));
    }
    check_all(&outputs, &also)
}

fn simulate(a: &SimulateArgs) -> anyhow::Result<()> {
    if !(2..=100_000).contains(&a.samples) {
        anyhow::bail!("--samples {} must be within 2..100000", a.samples);
    }
    check_outputs(Some(&a.out), a.plot.as_deref())?;
    let (inhale, exhale, b, name) = simulate_constants(a)?;
    let steps = a.samples - 1;
    let up =
        phase_curve(&inhale, steps).map_err(|e| anyhow::anyhow!("inhalation constants: {e}"))?;
    let down =
        phase_curve(&exhale, steps).map_err(|e| anyhow::anyhow!("exhalation constants: {e}"))?;
    let (d_up, _) = control_curve(&inhale, steps)?;
    let (d_down, _) = control_curve(&exhale, steps)?;
    let pressure = |x: f64| b.rp_cmh2o + (b.tp_cmh2o - b.rp_cmh2o) * x;
    let mut rows = Vec::new();
    for i in 0..=steps {
        let t = i as f64 / steps as f64;
        rows.push((
            "inhale",
            t,
            pressure(t),
            b.frc_ml + b.tv_ml * up[i],
            d_up[i],
        ));
    }
    for i in 0..=steps {
        let s = i as f64 / steps as f64;
        rows.push((
            "exhale",
            s,
            pressure(1.0 - s),
            b.frc_ml + b.tv_ml * (1.0 - down[i]),
            d_down[i],
        ));
    }
    // The plot is drawn first (to temporary files), the CSV written, then the plot put in place:
    // a plot that cannot be drawn leaves every output as it was.
    let mut staged = None;
    if let Some(png) = &a.plot {
        let series =
            |phase: &str, color, f: &dyn Fn(&(&str, f64, f64, f64, f64)) -> (f64, f64)| Series {
                label: if phase == "inhale" {
                    "inhalation"
                } else {
                    "exhalation"
                }
                .to_string(),
                points: rows.iter().filter(|r| r.0 == phase).map(f).collect(),
                color,
                markers: false,
            };
        let k = &inhale;
        let panels = [
            Panel {
                title: format!("PV loop: {name}"),
                x_label: "pressure (cmH2O)".into(),
                y_label: "volume (ml)".into(),
                series: vec![
                    series("inhale", INHALE, &|r| (r.2, r.3)),
                    series("exhale", EXHALE, &|r| (r.2, r.3)),
                ],
            },
            Panel {
                title: format!(
                    "damping D (eq. 5.11), q = {}, c = {}, T_ext = {}",
                    k.q, k.c, k.t_ext
                ),
                x_label: "normalised phase time".into(),
                y_label: "D (normalised)".into(),
                series: vec![
                    series("inhale", INHALE, &|r| (r.1, r.4)),
                    series("exhale", EXHALE, &|r| (r.1, r.4)),
                ],
            },
        ];
        staged = Some(plot::render(png, &panels)?);
    }
    outfile::write_atomically(&a.out, |w| {
        use std::io::Write;
        writeln!(w, "phase,t,pressure_cmh2o,volume_ml,damping")?;
        for (phase, t, p, v, d) in &rows {
            writeln!(w, "{phase},{t},{p},{v},{d}")?;
        }
        Ok(())
    })?;
    let plots = match staged {
        Some(s) => s
            .commit()?
            .iter()
            .map(|p| p.display().to_string())
            .collect(),
        None => Vec::new(),
    };
    let summary = SimulateSummary {
        csv: a.out.display().to_string(),
        plots,
        rows: rows.len(),
    };
    if a.json {
        println!("{}", serde_json::to_string(&summary)?);
    } else {
        println!(
            "wrote {} ({} rows: phase, t, pressure_cmh2o, volume_ml, damping)",
            summary.csv, summary.rows
        );
        for p in &summary.plots {
            println!("wrote {p}");
        }
    }
    Ok(())
}

#[derive(Serialize)]
struct PhaseJson {
    constants: PhaseConstants,
    rms_percent: f64,
    max_error_percent: f64,
    condition_number: f64,
    samples: usize,
}

impl From<&PhaseFit> for PhaseJson {
    fn from(f: &PhaseFit) -> Self {
        Self {
            constants: f.constants.clone(),
            rms_percent: f.rms_percent,
            max_error_percent: f.max_error_percent,
            condition_number: f.condition_number,
            samples: f.samples,
        }
    }
}

#[derive(Serialize)]
struct FitJson {
    rms_percent: f64,
    inhale: PhaseJson,
    exhale: PhaseJson,
    boundary: Boundary,
    driving_pressure_sign: f64,
    volume_unit: lung_bake::pv::curve::ColumnUnit,
    pressure_unit: lung_bake::pv::curve::ColumnUnit,
    q_chosen_by_fit: bool,
    c_chosen_by_fit: bool,
    seconds: f64,
    constants_file: Option<String>,
    plots: Vec<String>,
}

fn fit(a: &FitArgs) -> anyhow::Result<()> {
    let unit: Option<VolumeUnit> = crate::mask_cmd::parsed(a.volume_unit.as_deref())?;
    if let Some(frc) = a.frc {
        lung_model::plausible::FRC_ML.check(frc, Some("--frc is the FRC in ml".into()))?;
    }
    // The constants held fixed, in their documented ranges, and every output, before any work.
    if let Some(q) = a.q {
        lung_model::pv::check_q(q).map_err(|e| anyhow::anyhow!("--q: {e}"))?;
    }
    if let Some(c) = a.c {
        lung_model::pv::check_c(c).map_err(|e| anyhow::anyhow!("--c: {e}"))?;
    }
    lung_model::pv::check_t_ext(a.t_ext).map_err(|e| anyhow::anyhow!("--t-ext: {e}"))?;
    check_outputs(a.out.as_deref(), a.plot.as_deref())?;
    let curve = read_curve(
        &a.input,
        &lung_bake::pv::curve::CurveOptions {
            volume_unit: unit,
            frc_ml: a.frc,
            relative: a.relative,
            limits: a.input_args.limits(lung_model::input::ReadLimits::TABLE),
        },
    )?;
    if !a.json {
        say_units(&curve);
    }
    let opts = FitOptions {
        q: a.q,
        c: a.c,
        t_ext: a.t_ext,
        ..Default::default()
    };
    if !a.json {
        eprintln!(
            "lungdyn: fitting {} samples ({} vs {}) ...",
            curve.samples.len(),
            curve.pressure_column,
            curve.volume_column,
        );
    }
    let start = std::time::Instant::now();
    let fit = fit_curve(&curve.samples, &opts)
        .map_err(|e| anyhow::anyhow!("{}: {e}", a.input.display()))?;
    // What is written must be usable and plausible (the scene loader checks it again).
    fit.boundary
        .check_plausible()
        .map_err(|e| anyhow::anyhow!("{}: the fitted boundary values: {e}", a.input.display()))?;
    for f in [&fit.inhale, &fit.exhale] {
        if !(f.rms_percent.is_finite() && f.max_error_percent.is_finite()) {
            anyhow::bail!(
                "{}: the fit did not converge to a finite error (RMS {}): check the curve",
                a.input.display(),
                f.rms_percent
            );
        }
    }
    let seconds = start.elapsed().as_secs_f64();
    // Plot drawn first (temporary files), constants written, then the plot put in place.
    let staged = match &a.plot {
        Some(png) => Some(plot::render(png, &fit_panels(&fit, &curve.samples)?)?),
        None => None,
    };
    if let Some(out) = &a.out {
        PvConstantsFile {
            format: CONSTANTS_FORMAT,
            source: format!(
                "lungdyn pv fit --input {}{}",
                a.input.display(),
                if fit.driving_pressure_sign < 0.0 {
                    "; pressure fell as volume rose (oesophageal/pleural): RP and TP are the driving \
                     pressure -P"
                } else {
                    ""
                }
            ),
            boundary: fit.boundary,
            inhale: fit.inhale.constants.clone(),
            exhale: fit.exhale.constants.clone(),
        }
        .save(out)?;
    }
    let plots: Vec<String> = match staged {
        Some(s) => s
            .commit()?
            .iter()
            .map(|p| p.display().to_string())
            .collect(),
        None => Vec::new(),
    };
    let report = FitJson {
        rms_percent: fit.rms_percent,
        inhale: (&fit.inhale).into(),
        exhale: (&fit.exhale).into(),
        boundary: fit.boundary,
        driving_pressure_sign: fit.driving_pressure_sign,
        volume_unit: curve.volume_unit,
        pressure_unit: curve.pressure_unit,
        q_chosen_by_fit: a.q.is_none(),
        c_chosen_by_fit: a.c.is_none(),
        seconds,
        constants_file: a.out.as_ref().map(|p| p.display().to_string()),
        plots,
    };
    if a.json {
        println!("{}", serde_json::to_string(&report)?);
        return Ok(());
    }
    print_fit(a, &fit, seconds, &report);
    Ok(())
}

/// Say how the curve's columns were read: units converted or assumed, FRC added.
fn say_units(curve: &lung_bake::pv::curve::CurveFile) {
    for (col, what, u, to) in [
        (
            &curve.pressure_column,
            "pressure",
            curve.pressure_unit,
            "cmH2O",
        ),
        (&curve.volume_column, "volume", curve.volume_unit, "ml"),
    ] {
        if u.factor != 1.0 {
            eprintln!(
                "lungdyn: {what} column {col:?} is in {} ({}): converted to {to} (x{})",
                u.name, u.from, u.factor
            );
        } else if u.from == "default" {
            eprintln!(
                "lungdyn: {what} column {col:?} names no unit: read as {to} (name it in the header to be sure)"
            );
        }
    }
    if let Some(frc) = curve.frc_added_ml {
        let why = match curve.relative {
            Some(("header", _)) => format!(" (the header {:?} says so)", curve.volume_column),
            Some(("--relative", _)) => " (--relative)".to_string(),
            _ => String::new(),
        };
        eprintln!("lungdyn: volumes are changes above FRC{why}: {frc} ml added to each");
        if curve.relative.is_some_and(|r| r.1) {
            eprintln!(
                "lungdyn: FRC not given: Table 5.2's {frc} ml assumed (pass --frc ML for this \
                 patient's FRC; the fitted shape does not depend on it, the boundary values do)"
            );
        }
    }
}

/// The fit for a person: each phase's error and constants, the boundary values, what was written.
fn print_fit(a: &FitArgs, fit: &lung_bake::pv::fit::CurveFit, seconds: f64, report: &FitJson) {
    println!("fit of {} ({:.2} s)", a.input.display(), seconds);
    if fit.driving_pressure_sign < 0.0 {
        println!(
            "pressure falls as volume rises (oesophageal/pleural): fitted the driving pressure −P \
             (RP and TP below are −P)"
        );
    }
    for (name, f) in [("inhalation", &fit.inhale), ("exhalation", &fit.exhale)] {
        let k = &f.constants;
        println!(
            "  {name:<11} RMS {:.3} % (max {:.3} %) of the normalised range, {} samples, condition number {:.3e}",
            f.rms_percent, f.max_error_percent, f.samples, f.condition_number
        );
        println!(
            "              chi = [{}]",
            k.chi
                .iter()
                .map(|c| format!("{c:.5}"))
                .collect::<Vec<_>>()
                .join(", ")
        );
        println!(
            "              q = {:.4}{}, c = {:.4}{}, T_ext = {}, beta0 = {:.4}, beta1 = {:.4}",
            k.q,
            if a.q.is_none() {
                " (chosen by the fit)"
            } else {
                ""
            },
            k.c,
            if a.c.is_none() {
                " (chosen by the fit)"
            } else {
                ""
            },
            k.t_ext,
            k.beta0,
            k.beta1
        );
    }
    let b = &fit.boundary;
    println!(
        "  boundary    FRC {:.1} ml, TV {:.1} ml, RP {:.3} cmH2O, TP {:.3} cmH2O",
        b.frc_ml, b.tv_ml, b.rp_cmh2o, b.tp_cmh2o
    );
    println!("  overall RMS (worse phase) {:.3} %", fit.rms_percent);
    if let Some(out) = &a.out {
        println!("wrote {}", out.display());
    }
    for p in &report.plots {
        println!("wrote {p}");
    }
}

fn fit_panels(
    fit: &CurveFit,
    samples: &[lung_bake::pv::fit::PvSample],
) -> anyhow::Result<[Panel; 2]> {
    let grid: Vec<f64> = (0..=200).map(|i| i as f64 / 200.0).collect();
    let mut loop_series = vec![Series {
        label: "measured".into(),
        points: samples.iter().map(|s| (s.pressure, s.volume)).collect(),
        color: DATA,
        markers: true,
    }];
    let mut norm_series = Vec::new();
    for (i, (f, color, label)) in [
        (&fit.inhale, INHALE, "inhalation"),
        (&fit.exhale, EXHALE, "exhalation"),
    ]
    .into_iter()
    .enumerate()
    {
        let model = model_at(&f.constants, &grid, 400)?;
        let scale = &fit.scales[i];
        loop_series.push(Series {
            label: format!("{label} fit ({:.2} % RMS)", f.rms_percent),
            points: grid
                .iter()
                .zip(&model)
                .map(|(&t, &v)| scale.to_data(t, v))
                .collect(),
            color,
            markers: false,
        });
        norm_series.push(Series {
            label: format!("{label} data"),
            points: fit.limbs[i]
                .t
                .iter()
                .copied()
                .zip(fit.limbs[i].v.iter().copied())
                .collect(),
            color: DATA,
            markers: true,
        });
        norm_series.push(Series {
            label: format!("{label} model"),
            points: grid.iter().copied().zip(model).collect(),
            color,
            markers: false,
        });
    }
    Ok([
        Panel {
            title: "PV loop: measured and fitted".into(),
            x_label: "pressure (cmH2O)".into(),
            y_label: "volume (ml)".into(),
            series: loop_series,
        },
        Panel {
            title: "limbs in model coordinates".into(),
            x_label: "normalised phase time (driving pressure)".into(),
            y_label: "normalised volume".into(),
            series: norm_series,
        },
    ])
}
