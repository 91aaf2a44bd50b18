//! `lungdyn breathing sites FILE`: how remote sites follow a live patient (issue 35). A source
//! engine follows FILE replayed as its live signal (as the bridge replays it: each sample in the
//! first frame at or after its time), publishing its control states as in a shared session; a site
//! engine takes each state a network delay late and plays the patient's breath it carries
//! (format v4: the previous breath from the start of the one in progress). Per delay: the site's
//! volume against the source's (RMS, % of the recording's tidal volume), the same for a site
//! without the patient's breath (the model's own, as every site showed before v4), the best-fitting
//! lag and the largest tick-to-tick step. The engines are the real ones
//! (`engine::runtime::sites`), run as fast as they compute: no network, no clock.

use std::path::PathBuf;

use anyhow::Context;
use engine::runtime::sites::{self, SignalReplay, SiteFigures};
use engine::runtime::EngineCore;
use ipc_types::signal_unit;
use lung_model::breathing::check::read_trace_or_recording;
use lung_model::breathing::follow::Calibration;
use lung_model::breathing::trace::SignalUnit;
use lung_model::scene::{BreathSource, Scene, SceneExt};
use serde::Serialize;

/// Options of `lungdyn breathing sites`.
#[derive(Debug, Clone, clap::Args)]
pub struct SitesArgs {
    /// A respiratory recording, as `lungdyn breathing check` reads it (a ventilator's, a Varian RPM
    /// .vxp, or a CSV of one signal), replayed as the source's live signal.
    pub file: PathBuf,
    /// Network delays from the source to a site, ms (a state arrives this long after the tick it
    /// was made at; a LAN is under 5, a continent 50–150, a poor link 250 and more).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "0,50,100,250,1000",
        value_name = "MS"
    )]
    pub delay_ms: Vec<f64>,
    /// The session's scene (its lungs, [pv], [engine] tick rate and [breathing] predictor and
    /// latency); the built-in default without it. Its [breathing] source is set to the signal here.
    #[arg(long, value_name = "TOML")]
    pub scene: Option<PathBuf>,
    /// The tidal volume a one-signal trace's typical breath is calibrated to in hindsight, ml (the
    /// percentages' denominator for such a trace; a ventilator's recording has its own).
    #[arg(long, default_value_t = 500.0, value_name = "ML")]
    pub tidal_ml: f64,
    /// Folder for the kernels the scene lacks (baked once, as `lungdyn scene prepare` bakes them).
    #[arg(long, default_value = "out/kernels", value_name = "DIR")]
    pub kernels: PathBuf,
    /// Write every tick of the first delay's run as CSV: `t_s,source_ml,site_ml,model_site_ml`
    /// (each the volume above FRC of both lungs; the model site's is a site without the
    /// patient's breath), to lay over the recording.
    #[arg(long, value_name = "CSV")]
    pub ticks_out: Option<PathBuf>,
    /// Print one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
    /// Input size limit and special files.
    #[command(flatten)]
    pub input_args: crate::input_args::InputArgs,
}

/// One delay's figures.
#[derive(Debug, Clone, Serialize)]
pub struct SitesRow {
    /// The delay, ms (rounded to whole ticks: `delay_ticks`).
    pub delay_ms: f64,
    /// The delay in ticks.
    pub delay_ticks: u64,
    /// RMS of the site's volume against the source's while both follow the patient, % of the
    /// tidal volume.
    pub rms_percent_of_tidal: f64,
    /// The same ticks for a site without the patient's breath (the model's own breath).
    pub rms_percent_of_tidal_model: f64,
    /// Over every tick the source followed (the site's model before its first whole breath
    /// included).
    pub rms_percent_of_tidal_all: f64,
    /// The figures behind them (ml, ms, ticks).
    pub figures: SiteFigures,
    /// How late the patient's turns (a breath's start, its peak) reached the site after the tick
    /// they happened at, ms: mean and largest (the source's confirmation plus the delay).
    pub turn_heard_after_ms: Option<f64>,
    /// The largest.
    pub turn_heard_after_max_ms: f64,
}

/// What `lungdyn breathing sites` reports.
#[derive(Debug, Clone, Serialize)]
pub struct SitesReport {
    /// The file.
    pub file: String,
    /// What it was read as.
    pub kind: String,
    /// Seconds replayed.
    pub duration_s: f64,
    /// The recording's mean tidal volume, ml (the percentages' denominator).
    pub tidal_ml: f64,
    /// The engine's tick rate, Hz.
    pub tick_hz: f64,
    /// Control states the source sent, and how many carried the patient's breath.
    pub states: usize,
    /// Of them, carrying the patient's breath.
    pub states_with_breath: usize,
    /// Seconds from the start to the site's first tick following the patient (no delay).
    pub site_following_from_s: Option<f64>,
    /// Per delay.
    pub rows: Vec<SitesRow>,
}

fn check_args(a: &SitesArgs) -> anyhow::Result<()> {
    if a.delay_ms.is_empty() {
        anyhow::bail!("--delay-ms: give at least one delay, e.g. --delay-ms 100");
    }
    for &d in &a.delay_ms {
        if !(d.is_finite() && (0.0..=10_000.0).contains(&d)) {
            anyhow::bail!(
                "--delay-ms {d}: a network delay is 0…10000 ms (a continent is 50–150 ms)"
            );
        }
    }
    if let Some(p) = &a.ticks_out {
        // Written when the runs end: anything that would refuse it refuses before any work.
        crate::outputs::check(&crate::outputs::Output {
            flag: "--ticks-out",
            path: p,
            extensions: &["csv"],
        })?;
    }
    if !(a.tidal_ml.is_finite() && (50.0..=3000.0).contains(&a.tidal_ml)) {
        anyhow::bail!(
            "--tidal-ml {}: an adult's tidal volume is 300–800 ml, a child's from 50 (50…3000 accepted)",
            a.tidal_ml
        );
    }
    Ok(())
}

/// Run `lungdyn breathing sites`.
pub fn sites(a: &SitesArgs) -> anyhow::Result<SitesReport> {
    check_args(a)?;
    let bytes = lung_model::input::read_bounded(
        &a.file,
        a.input_args.limits(lung_model::input::ReadLimits::TABLE),
    )?;
    let read = read_trace_or_recording(
        &a.file,
        &bytes,
        Calibration::Auto {
            tidal_ml: a.tidal_ml,
        },
    )?;
    let trace = &read.trace;
    let mut scene = Scene::load_or_default(a.scene.as_deref())?;
    if scene.remote.is_some() {
        // The session's own keys play no part here: the engines run in this process.
        scene.remote = None;
    }
    crate::prepare::ensure_kernels(&mut scene, &a.kernels)
        .context("the kernels of the session's lungs")?;
    let mut source_scene = scene.clone();
    source_scene.breathing.source = BreathSource::Signal;
    source_scene.breathing.signal = format!("trace:{}", a.file.display());
    source_scene
        .validate()
        .map_err(|e| anyhow::anyhow!("the scene following {}: {e}", a.file.display()))?;
    let mut site_scene = scene;
    site_scene.breathing.source = BreathSource::Model;
    let source = EngineCore::new(&source_scene)?;
    let site = EngineCore::new(&site_scene)?;
    let tick_hz = source_scene.engine.tick_hz;
    let unit = match read.unit {
        SignalUnit::Mm => signal_unit::MM,
        SignalUnit::Ml => signal_unit::ML,
        SignalUnit::Arbitrary => signal_unit::ARBITRARY,
    };
    let period_ns = (1e9 / trace.rate_hz).round() as u64;
    let n = trace.samples.len();
    let duration_s = (trace.samples[n - 1].t_ns - trace.samples[0].t_ns) as f64 * 1e-9;
    let ticks = (duration_s * tick_hz).floor() as u64 + 1;
    let mut rows = Vec::new();
    let mut first = None;
    let mut states = (0, 0);
    for &delay_ms in &a.delay_ms {
        let delay_ticks = (delay_ms * 1e-3 * tick_hz).round() as u64;
        let mut replay = SignalReplay::new(&trace.samples, unit, period_ns, tick_hz);
        let run = sites::follow(
            source.clone(),
            site.clone(),
            &mut |t| replay.frame(t),
            ticks,
            delay_ticks,
            tick_hz,
        )?;
        if rows.is_empty() {
            if let Some(path) = &a.ticks_out {
                let mut csv = String::from("t_s,source_ml,site_ml,model_site_ml\n");
                for t in &run.ticks {
                    csv += &format!(
                        "{:.4},{:.3},{:.3},{:.3}\n",
                        t.t_s, t.source_ml, t.site_ml, t.model_site_ml
                    );
                }
                outfile::write_atomically(path, |w| std::io::Write::write_all(w, csv.as_bytes()))
                    .with_context(|| format!("--ticks-out {}", path.display()))?;
            }
            states = (
                run.states.len(),
                run.states.iter().filter(|s| s.live.is_some()).count(),
            );
            first = run
                .ticks
                .iter()
                .find(|t| t.site_state & ipc_types::engine_state::SIGNAL_FOLLOWING != 0)
                .map(|t| t.t_s);
        }
        let figures = sites::figures(&run, 0.0, tick_hz);
        rows.push(SitesRow {
            delay_ms,
            delay_ticks,
            rms_percent_of_tidal: 100.0 * figures.rms_ml / trace.tidal_ml,
            rms_percent_of_tidal_model: 100.0 * figures.model_rms_ml / trace.tidal_ml,
            rms_percent_of_tidal_all: 100.0 * figures.rms_all_ml / trace.tidal_ml,
            figures,
            turn_heard_after_ms: run.turn_lag.mean_ms(tick_hz),
            turn_heard_after_max_ms: run.turn_lag.max_ticks as f64 * 1e3 / tick_hz,
        });
    }
    Ok(SitesReport {
        file: a.file.display().to_string(),
        kind: read.kind,
        duration_s,
        tidal_ml: trace.tidal_ml,
        tick_hz,
        states: states.0,
        states_with_breath: states.1,
        site_following_from_s: first,
        rows,
    })
}

/// The report for a person.
pub fn sites_text(r: &SitesReport) -> String {
    let mut s = format!(
        "{} ({}): {:.1} s, tidal volume {:.0} ml, engines at {:.0} Hz\n\
         the source sent {} control states, {} with the patient's breath; {}\n\n\
         RMS of the site's volume against the source's, % of the tidal volume:\n\
         delay     following   its model   every tick      lag   largest step (site / source)   ticks the site followed   turns heard after (mean, max)\n",
        r.file,
        r.kind,
        r.duration_s,
        r.tidal_ml,
        r.tick_hz,
        r.states,
        r.states_with_breath,
        r.site_following_from_s.map_or("no site follows the patient".to_string(), |t| format!(
            "a site follows the patient from {t:.1} s"
        )),
    );
    // A figure over no tick (the site never followed) is none, not NaN.
    let or_none = |x: f64, width: usize, unit: &str| {
        if x.is_finite() {
            format!("{x:>width$.1} {unit}")
        } else {
            format!("{:>w$}", "—", w = width + 1 + unit.chars().count())
        }
    };
    for row in &r.rows {
        let f = &row.figures;
        let followed = f.site_following > 0;
        s += &format!(
            "{:>5.0} ms {} {} {} {} {:>14.1} / {:.1} ml {:>16} of {:<6} {}\n",
            row.delay_ms,
            or_none(row.rms_percent_of_tidal, 9, "%"),
            or_none(row.rms_percent_of_tidal_model, 9, "%"),
            or_none(row.rms_percent_of_tidal_all, 10, "%"),
            if followed {
                format!("{:>6.0} ms", f.lag_ms)
            } else {
                format!("{:>9}", "—")
            },
            f.largest_step_ml,
            f.source_largest_step_ml,
            f.site_following,
            f.ticks,
            row.turn_heard_after_ms
                .map_or(format!("{:>11}", "none"), |m| format!(
                    "{m:>8.0} ms, {:.0} ms",
                    row.turn_heard_after_max_ms
                )),
        );
    }
    let none: Vec<String> = r
        .rows
        .iter()
        .filter(|row| row.figures.site_following == 0)
        .map(|row| format!("{:.0} ms", row.delay_ms))
        .collect();
    if r.states_with_breath == 0 {
        s += &format!(
            "\nNo site follows the patient: the source sent 0 of its {} states with the patient's \
             breath (a site needs one whole breath the source followed, from one end-expiration \
             its follower confirmed to the next), so every site breathed the model and there is \
             nothing to compare while following.\n",
            r.states
        );
    } else if !none.is_empty() {
        s += &format!(
            "\nAt {} the site followed no tick the source followed: the patient's breath reached \
             it too late in the recording.\n",
            none.join(", ")
        );
    }
    s += "\n\"following\": the ticks the source and the site both followed the patient; \"its model\": \
          the same ticks on a site without the patient's breath (the model's own clock); \"every \
          tick\": every tick the source followed, the site's model before its first whole breath \
          included. A site plays the previous breath from the patient's last turn, and the next on the \
          patient's rhythm once that one has played out (docs/REMOTE.md, \"A live patient\").\n";
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(delay_ms: f64, followed: bool) -> SitesRow {
        let nan_unless = |x: f64| if followed { x } else { f64::NAN };
        SitesRow {
            delay_ms,
            delay_ticks: (delay_ms * 0.06).round() as u64,
            rms_percent_of_tidal: nan_unless(12.1),
            rms_percent_of_tidal_model: nan_unless(47.4),
            rms_percent_of_tidal_all: 55.5,
            figures: SiteFigures {
                ticks: 1021,
                site_following: if followed { 806 } else { 0 },
                rms_ml: nan_unless(53.0),
                model_rms_ml: nan_unless(207.6),
                rms_all_ml: 285.1,
                lag_ms: nan_unless(17.0),
                largest_step_ml: 10.4,
                source_largest_step_ml: 56.8,
            },
            turn_heard_after_ms: followed.then_some(158.0),
            turn_heard_after_max_ms: if followed { 200.0 } else { 0.0 },
        }
    }

    fn report(followed: bool) -> SitesReport {
        SitesReport {
            file: "rec.csv".into(),
            kind: "ventilator recording".into(),
            duration_s: 21.5,
            tidal_ml: 513.0,
            tick_hz: 60.0,
            states: 5,
            states_with_breath: if followed { 4 } else { 0 },
            site_following_from_s: followed.then_some(6.5),
            rows: vec![row(0.0, followed), row(1000.0, followed)],
        }
    }

    /// A recording on which the site never followed (the source never sent a whole breath: found
    /// on the shared COPD ventilator recording) reports none and says why, never "NaN %".
    #[test]
    fn a_site_that_never_followed_is_said_not_printed_as_nan() {
        let text = sites_text(&report(false));
        assert!(!text.contains("NaN"), "{text}");
        assert!(text.contains("No site follows the patient"), "{text}");
        assert!(text.contains("0 of its 5 states"), "{text}");
        assert!(text.contains("no site follows the patient"), "{text}");
        let json = serde_json::to_value(report(false)).unwrap();
        assert!(json["rows"][0]["rms_percent_of_tidal"].is_null(), "{json}");
        assert!(json["rows"][0]["figures"]["lag_ms"].is_null(), "{json}");
        // A site that followed: its figures, and no such sentence.
        let text = sites_text(&report(true));
        assert!(text.contains("12.1 %") && text.contains("17 ms"), "{text}");
        assert!(text.contains("158 ms, 200 ms"), "{text}");
        assert!(
            text.contains("a site follows the patient from 6.5 s"),
            "{text}"
        );
        assert!(
            !text.contains("No site follows") && !text.contains("NaN"),
            "{text}"
        );
        // Breaths sent, and one delay too long for the recording: said for that delay.
        let mut late = report(true);
        late.rows[1] = row(1000.0, false);
        let text = sites_text(&late);
        assert!(
            text.contains("At 1000 ms the site followed no tick"),
            "{text}"
        );
        assert!(!text.contains("NaN"), "{text}");
    }
}
