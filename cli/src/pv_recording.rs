//! `lungdyn pv recording FILE`: a ventilator recording cut into breaths, each characterised (timing,
//! pressures, the equation of motion, a class with its reason, the PV model's fit where it applies).

use std::path::PathBuf;

use lung_bake::pv::fit::{model_at, FitOptions};
use lung_bake::pv::recording::{analyse, AnalyseOptions, BreathClass, BreathReport, PvOutcome};
use lung_model::recording::{read_recording, ColumnNote, Format, Recording};
use serde::Serialize;

use crate::plot::{self, Panel, Series, DATA, EXHALE, INHALE};

/// Options of `lungdyn pv recording`.
#[derive(Debug, Clone, clap::Args)]
pub struct RecordingArgs {
    /// The recording: a Puritan-Bennett 840 raw export (`BS, S:<n>,` … `flow, pressure` … `BE`,
    /// 50 Hz, L/min and cmH2O) or a CSV whose header names each column with its unit: time
    /// (time_s, t_ms), flow (flow_L/min, flow (L/s), flow_ml_s; + = inspiration), airway pressure
    /// (paw_cmH2O, pressure (kPa), Paw mbar); optional volume_ml and oesophageal pressure
    /// (pes_cmH2O). A column without a recognised unit is refused.
    pub file: PathBuf,
    /// Plot waveforms with breath marks, the loops overlaid and the fitted models (PNG; an SVG is
    /// written beside it).
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Print one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
    /// Fix q of the PV fits (else each fit chooses it).
    #[arg(long)]
    pub q: Option<f64>,
    /// Fix c of the PV fits (else each fit chooses it).
    #[arg(long)]
    pub c: Option<f64>,
    /// Input size limit and special files.
    #[command(flatten)]
    pub input_args: crate::input_args::InputArgs,
}

#[derive(Serialize)]
struct BreathJson {
    index: usize,
    vent_breath: Option<u64>,
    start_s: f64,
    duration_s: f64,
    tidal_volume_ml: f64,
    rate_per_min: f64,
    inspiration_s: f64,
    expiration_s: f64,
    /// I:E is 1 : this.
    ie_ratio: f64,
    pip_cmh2o: f64,
    peep_cmh2o: f64,
    inspired_ml: f64,
    drift_ml: f64,
    compliance_ml_per_cmh2o: Option<f64>,
    resistance_cmh2o_s_per_l: Option<f64>,
    eom_residual_percent: Option<f64>,
    class: BreathClass,
    reason: String,
    rms_percent: Option<f64>,
    pv_fit: Option<PvFitJson>,
    pv_not_fitted: Option<String>,
}

#[derive(Serialize)]
struct PvFitJson {
    inhale_rms_percent: f64,
    exhale_rms_percent: f64,
    inhale: lung_model::pv::PhaseConstants,
    exhale: lung_model::pv::PhaseConstants,
}

#[derive(Serialize)]
struct RecordingJson {
    file: String,
    format: Format,
    columns: Vec<ColumnNote>,
    samples: usize,
    sample_rate_hz: f64,
    duration_s: f64,
    ventilator_breaths: usize,
    breaths: Vec<BreathJson>,
    plots: Vec<String>,
}

fn breath_json(b: &BreathReport) -> BreathJson {
    let t = &b.timing;
    let (pv_fit, pv_not_fitted) = match &b.pv {
        PvOutcome::Fitted(f) => (
            Some(PvFitJson {
                inhale_rms_percent: f.inhale.rms_percent,
                exhale_rms_percent: f.exhale.rms_percent,
                inhale: f.inhale.constants.clone(),
                exhale: f.exhale.constants.clone(),
            }),
            None,
        ),
        PvOutcome::NotApplicable(why) => (None, Some(why.clone())),
    };
    BreathJson {
        index: b.index,
        vent_breath: b.vent_breath,
        start_s: t.start_s,
        duration_s: t.duration_s,
        tidal_volume_ml: t.tidal_volume_ml,
        rate_per_min: t.rate_per_min,
        inspiration_s: t.inspiration_s,
        expiration_s: t.expiration_s,
        ie_ratio: b.ie_ratio(),
        pip_cmh2o: b.pip_cmh2o,
        peep_cmh2o: b.peep_cmh2o,
        inspired_ml: t.inspired_ml,
        drift_ml: t.net_ml,
        compliance_ml_per_cmh2o: b.eom.map(|e| e.compliance_ml_per_cmh2o),
        resistance_cmh2o_s_per_l: b.eom.map(|e| e.resistance_cmh2o_s_per_l),
        eom_residual_percent: b.eom.map(|e| e.residual_percent),
        class: b.class,
        reason: b.reason.clone(),
        rms_percent: b.pv_rms_percent(),
        pv_fit,
        pv_not_fitted,
    }
}

/// Run `lungdyn pv recording`.
pub fn run(a: &RecordingArgs) -> anyhow::Result<()> {
    if let Some(q) = a.q {
        lung_model::pv::check_q(q).map_err(|e| anyhow::anyhow!("--q: {e}"))?;
    }
    if let Some(c) = a.c {
        lung_model::pv::check_c(c).map_err(|e| anyhow::anyhow!("--c: {e}"))?;
    }
    if let Some(p) = &a.plot {
        plot::check_path(p)?;
    }
    let rec = read_recording(
        &a.file,
        a.input_args.limits(lung_model::input::ReadLimits::TABLE),
    )?;
    let opts = AnalyseOptions {
        fit: FitOptions {
            q: a.q,
            c: a.c,
            ..Default::default()
        },
        ..Default::default()
    };
    // Units and signs first, from the breaths' characters (cheap): the PV fits of a recording in the
    // wrong unit take seconds each and would only be thrown away.
    let characters = lung_model::recording::classify::characterise_all(&rec, &opts.segment);
    lung_model::recording::checks::check_plausible(&rec, &characters.iter().collect::<Vec<_>>())
        .map_err(|e| anyhow::anyhow!("{}: {e}", a.file.display()))?;
    let reports = analyse(&rec, &opts);
    if reports.is_empty() {
        anyhow::bail!(
            "{}: no breath found: the flow never rises above +{} L/min for {} s and falls below it \
             again (is the flow column the airway flow, + = inspiration?)",
            a.file.display(),
            opts.segment.threshold_lps * 60.0,
            opts.segment.min_inspiration_s
        );
    }
    let staged = match &a.plot {
        Some(png) => Some(plot::render(png, &panels(&rec, &reports)?)?),
        None => None,
    };
    let plots: Vec<String> = match staged {
        Some(s) => s
            .commit()?
            .iter()
            .map(|p| p.display().to_string())
            .collect(),
        None => Vec::new(),
    };
    let n = rec.t_s.len();
    let duration = rec.t_s[n - 1] - rec.t_s[0];
    let report = RecordingJson {
        file: a.file.display().to_string(),
        format: rec.format,
        columns: rec.columns.clone(),
        samples: n,
        sample_rate_hz: (n - 1) as f64 / duration,
        duration_s: duration,
        ventilator_breaths: rec.vent_breaths.len(),
        breaths: reports.iter().map(breath_json).collect(),
        plots,
    };
    if a.json {
        println!("{}", serde_json::to_string(&report)?);
        return Ok(());
    }
    print_table(&report, &reports);
    Ok(())
}

fn print_table(r: &RecordingJson, reports: &[BreathReport]) {
    println!(
        "{}: {}, {} samples at {:.1} Hz ({:.1} s){}",
        r.file,
        r.format.describe(),
        r.samples,
        r.sample_rate_hz,
        r.duration_s,
        if r.ventilator_breaths > 0 {
            format!(", {} ventilator breaths (BS…BE)", r.ventilator_breaths)
        } else {
            String::new()
        }
    );
    for c in &r.columns {
        println!(
            "  {:<21} {:?} in {} (x{} to lungdyn's unit)",
            c.quantity, c.column, c.unit, c.factor
        );
    }
    let count = |c: BreathClass| reports.iter().filter(|b| b.class == c).count();
    println!(
        "  {} breaths: {} passive volume-controlled, {} passive pressure-controlled, {} patient effort, {} artefact",
        reports.len(),
        count(BreathClass::PassiveVolumeControlled),
        count(BreathClass::PassivePressureControlled),
        count(BreathClass::PatientEffort),
        count(BreathClass::Artefact)
    );
    println!(
        "  {:>3} {:>6} {:>7} {:>6} {:>6} {:>6} {:>5} {:>5} {:>7} {:>6} {:>6}  {:<10} {:>7}",
        "#",
        "vent",
        "start_s",
        "Vt_ml",
        "rate",
        "I:E",
        "PIP",
        "PEEP",
        "C_ml/cm",
        "R",
        "EoM_%",
        "class",
        "PV_RMS%"
    );
    let opt = |v: Option<f64>, p: usize| v.map_or("-".to_string(), |v| format!("{v:.p$}"));
    for (b, j) in reports.iter().zip(&r.breaths) {
        println!(
            "  {:>3} {:>6} {:>7.2} {:>6.1} {:>6.1} {:>6} {:>5.1} {:>5.1} {:>7} {:>6} {:>6}  {:<10} {:>7}",
            b.index,
            b.vent_breath.map_or("-".to_string(), |n| n.to_string()),
            j.start_s,
            j.tidal_volume_ml,
            j.rate_per_min,
            format!("1:{:.1}", j.ie_ratio),
            j.pip_cmh2o,
            j.peep_cmh2o,
            opt(j.compliance_ml_per_cmh2o, 1),
            opt(j.resistance_cmh2o_s_per_l, 1),
            opt(j.eom_residual_percent, 2),
            b.class.short(),
            opt(j.rms_percent, 2)
        );
    }
    println!("  (R in cmH2O·s/L; EoM_%: RMS residual of Paw = V/C + R·flow + P0 as % of the pressure swing; PV_RMS%: eq. 5.11 fit, worse limb)");
    for (b, j) in reports.iter().zip(&r.breaths) {
        println!("  {:>3} {}: {}", b.index, b.class.short(), b.reason);
        if let Some(why) = &j.pv_not_fitted {
            println!("      PV model not fitted: {why}");
        }
    }
    for p in &r.plots {
        println!("wrote {p}");
    }
}

/// Waveforms with breath marks, the loops overlaid by class, the fitted models.
fn panels(rec: &Recording, reports: &[BreathReport]) -> anyhow::Result<Vec<Panel>> {
    let t = &rec.t_s;
    let marks = |y: &dyn Fn(usize) -> f64| Series {
        label: "breath start".into(),
        points: reports
            .iter()
            .map(|b| (t[b.span.start], y(b.span.start)))
            .collect(),
        color: EXHALE,
        markers: true,
    };
    // Volume per breath, drift-corrected, end to end.
    let mut volume: Vec<(f64, f64)> = Vec::new();
    let mut eom_p: Vec<(f64, f64)> = Vec::new();
    for b in reports {
        for (j, v) in b.volume_ml.iter().enumerate() {
            let i = b.span.start + j;
            volume.push((t[i], *v));
            if let Some(e) = b.eom {
                eom_p.push((
                    t[i],
                    v / e.compliance_ml_per_cmh2o
                        + e.resistance_cmh2o_s_per_l * rec.flow_lps[i]
                        + e.p0_cmh2o,
                ));
            }
        }
    }
    let vol_at = |i: usize| {
        reports
            .iter()
            .find(|b| b.span.start == i)
            .map_or(0.0, |b| b.volume_ml[0])
    };
    let line = |label: &str, points: Vec<(f64, f64)>, color| Series {
        label: label.into(),
        points,
        color,
        markers: false,
    };
    let mut loops = Vec::new();
    for (class, color) in [
        (BreathClass::PassiveVolumeControlled, INHALE),
        (
            BreathClass::PassivePressureControlled,
            plotters::style::RGBColor(44, 160, 44),
        ),
        (
            BreathClass::PatientEffort,
            plotters::style::RGBColor(214, 39, 40),
        ),
        (BreathClass::Artefact, DATA),
    ] {
        let points: Vec<(f64, f64)> = reports
            .iter()
            .filter(|b| b.class == class)
            .flat_map(|b| {
                b.volume_ml
                    .iter()
                    .enumerate()
                    .map(move |(j, v)| (rec.paw_cmh2o[b.span.start + j], *v))
            })
            .collect();
        if !points.is_empty() {
            loops.push(line(class.short(), points, color));
        }
    }
    let grid: Vec<f64> = (0..=100).map(|i| i as f64 / 100.0).collect();
    let mut model = Vec::new();
    for b in reports {
        if let PvOutcome::Fitted(f) = &b.pv {
            for (k, limb) in [&f.inhale, &f.exhale].into_iter().enumerate() {
                let m = model_at(&limb.constants, &grid, 400)?;
                model.extend(
                    grid.iter()
                        .zip(&m)
                        .map(|(&x, &v)| f.scales[k].to_data(x, v)),
                );
            }
        }
    }
    if !model.is_empty() {
        loops.push(line("PV model fit (eq. 5.11)", model, EXHALE));
    }
    let mut pressure = vec![line(
        "measured",
        t.iter()
            .copied()
            .zip(rec.paw_cmh2o.iter().copied())
            .collect(),
        DATA,
    )];
    if !eom_p.is_empty() {
        pressure.push(line("V/C + R·flow + P0 (fit per breath)", eom_p, INHALE));
    }
    pressure.push(marks(&|i| rec.paw_cmh2o[i]));
    Ok(vec![
        Panel {
            title: "flow (+ inspiration)".into(),
            x_label: "time (s)".into(),
            y_label: "flow (L/s)".into(),
            series: vec![
                line(
                    "flow",
                    t.iter()
                        .copied()
                        .zip(rec.flow_lps.iter().copied())
                        .collect(),
                    DATA,
                ),
                marks(&|i| rec.flow_lps[i]),
            ],
        },
        Panel {
            title: "airway pressure and the equation of motion".into(),
            x_label: "time (s)".into(),
            y_label: "pressure (cmH2O)".into(),
            series: pressure,
        },
        Panel {
            title: "volume per breath (drift-corrected)".into(),
            x_label: "time (s)".into(),
            y_label: "volume above breath start (ml)".into(),
            series: vec![line("volume", volume, INHALE), marks(&vol_at)],
        },
        Panel {
            title: "loops by class, with the PV model's fits".into(),
            x_label: "airway pressure (cmH2O)".into(),
            y_label: "volume (ml)".into(),
            series: loops,
        },
    ])
}
