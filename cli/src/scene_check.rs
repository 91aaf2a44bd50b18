//! `lungdyn scene check FILE`: validate a scene (every key, every file it names, the `[disease]`
//! table against the scene's lungs) and report what it would simulate. For a disease state the
//! report is the disease model's course computed from the tick-independent library
//! (`lung_model::disease`, EQUATIONS.md §4): a closed pneumothorax's plan (eq. 8.1–8.9), a tension
//! pneumothorax cycle by cycle with the scene's timed interventions (eq. 8.10–8.13), a tumour's
//! parameters and raised resistance (eq. 8.9, 8.14–8.22). The engine runs every state
//! (`engine::runtime::disease`, the same course); a tumour's kernel change is baked into the affected
//! lung's kernel (`lungdyn scene prepare`, or `lungdyn bake --scene`), and `scene run` reports the
//! tumour centre's trajectory.

use std::path::PathBuf;

use anyhow::Context;
use lung_model::disease::tension::{Outcome, Tension};
use lung_model::disease::{LungBaseline, NormalBreathing};
use lung_model::mesh::{Side, TriMesh};
use lung_model::scene::Scene;
use lung_model::scene_disease::DiseaseSpec;
use serde_json::{json, Value};

/// Options of `lungdyn scene check`.
#[derive(Debug, Clone, clap::Args)]
pub struct CheckArgs {
    /// Scene file (TOML).
    pub file: PathBuf,
    /// Tension pneumothorax: breathing cycles to follow (the course stops earlier at arrest once
    /// every timed intervention has arrived).
    #[arg(long, default_value_t = 300, value_name = "N")]
    pub cycles: u32,
    /// Print one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

/// Most cycles `--cycles` may ask for (about 10 hours of breathing at 15/min).
pub const MAX_CYCLES: u32 = 10_000;

/// The lung surface the scene would use for `side`: the named kernel's, else the built-in lung at
/// the scene's resolution.
fn lung_mesh(scene: &Scene, side: Side) -> anyhow::Result<TriMesh> {
    match scene.lungs.kernels.get(side) {
        Some(k) => Ok(lung_model::kernel::KernelFile::open(k)
            .with_context(|| format!("{} lung kernel", side.name()))?
            .mesh()),
        None => lung_model::mesh::generate::lung(side, scene.lungs.vertices)
            .with_context(|| format!("the built-in {} lung", side.name())),
    }
}

fn r3(v: f64) -> f64 {
    (v * 1000.0).round() / 1000.0
}

/// Validate `args.file` and report.
pub fn run(args: &CheckArgs) -> anyhow::Result<Value> {
    if !(1..=MAX_CYCLES).contains(&args.cycles) {
        anyhow::bail!("--cycles {} must be within 1..{MAX_CYCLES}", args.cycles);
    }
    let scene = Scene::load(&args.file)?;
    let origin = args.file.display().to_string();
    let (inhale, exhale, boundary) = scene
        .pv_model()
        .with_context(|| format!("scene {origin}"))?;
    // The renderer's calibration and HMD optics files, loaded as the renderer loads them.
    let rig = renderer::camera::RigFiles::load(&scene.render, None, None)
        .with_context(|| format!("scene {origin}"))?;
    let render = json!({
        "calibration": rig.calibration.as_ref().map(|(p, _, c)| crate::register_cmd::calibration_json(p, c)),
        "hmd": rig.optics.as_ref().map(|(p, _, o)| crate::register_cmd::optics_json(Some(p), o)),
    });
    let mut timing = scene.timing();
    // A waveform scene breathes at its recording's rate and tidal volume (no PV model).
    let waveform = scene
        .pv_waveform()
        .with_context(|| format!("scene {origin}"))?;
    let (frc_ml, tv_ml) = match &waveform {
        Some(w) => {
            timing.breaths_per_min = w.rate_per_min;
            (boundary.frc_ml, w.tidal_volume_ml)
        }
        None => (boundary.frc_ml, boundary.tv_ml),
    };
    let sides: Vec<&str> = scene.lungs.sides.iter().map(|s| s.name()).collect();
    let mut out = json!({
        "scene": origin,
        "valid": true,
        "lungs": sides,
        "mode": format!("{:?}", scene.lungs.mode).to_lowercase(),
        "bands": scene.lungs.bands,
        "pv": {
            "preset": scene.pv.preset,
            "constants": scene.pv.constants.as_ref().map(|p| p.display().to_string()),
            "waveform": scene.pv.waveform.as_ref().map(|p| p.display().to_string()),
            "waveform_breaths_used": waveform.as_ref().map(|w| w.breaths_used),
            "frc_ml": frc_ml,
            "tidal_volume_ml": r3(tv_ml),
            "breaths_per_min": timing.breaths_per_min,
        },
        "render": render,
        "disease": Value::Null,
    });
    let Some(d) = &scene.disease else {
        return Ok(out);
    };
    let spec = d.validate(&scene.lungs.sides)?;
    let normal = NormalBreathing {
        inhale,
        exhale,
        boundary,
        timing,
    };
    let mut baselines = Vec::new();
    for &side in &scene.lungs.sides {
        let mesh = lung_mesh(&scene, side)?;
        let share = mesh.enclosed_volume_ml() / boundary.frc_ml;
        baselines.push(
            LungBaseline::of(&mesh, side, share)
                .with_context(|| format!("the {} lung's baseline", side.name()))?,
        );
    }
    out["disease"] = match &spec {
        DiseaseSpec::Closed(c) => closed(c, &normal, &baselines)?,
        DiseaseSpec::Tension {
            params,
            onset_s,
            events,
        } => tension(*params, *onset_s, events, &normal, &baselines, args.cycles)?,
        DiseaseSpec::Tumour(t) => tumour(t, &scene, &normal, &baselines)?,
    };
    out["disease"]["kind"] = json!(d.kind.name());
    out["disease"]["engine_applies_it"] = json!(true);
    Ok(out)
}

/// A tumour's report without baking: where its centre is, that it lies inside the lung, how many
/// surface vertices its expandability reaches, and the raised resistance (eq. 8.9).
fn tumour(
    t: &lung_model::disease::tumour::Tumour,
    scene: &Scene,
    normal: &NormalBreathing,
    lungs: &[LungBaseline],
) -> anyhow::Result<Value> {
    let mesh = lung_mesh(scene, t.side)?;
    // The bake's own check (parameters, lung, centre inside the surface), without the bake.
    lung_bake::kernel::check_tumour(t, t.side, &mesh).context("[disease.tumour]")?;
    let centre = t.centre_mm(&mesh);
    let lung = lungs
        .iter()
        .find(|b| b.side == t.side)
        .context("the tumour's lung is not in the scene")?;
    let (_, _, [ri, re]) = t.resistance(&normal.inhale, &normal.exhale, lung.start_volume_ml)?;
    let affected = t
        .expandability_of(&mesh)
        .iter()
        .filter(|&&a| a < 1.0)
        .count();
    Ok(json!({
        "side": t.side.name(),
        "centre": t.centre,
        "centre_mm": centre.map(r3),
        "radii_mm": t.radii_mm,
        "volume_ml": r3(t.volume_ml()),
        "expandability": t.expandability,
        "falloff": t.falloff,
        "coupling": t.coupling,
        "phi_variant": format!("{:?}", t.phi).to_lowercase(),
        "surface_vertices_affected": affected,
        "resistance_x": { "inhale": ri.x, "exhale": re.x },
        "note": if affected == 0 {
            "no surface vertex lies within the tumour's reach (radius x (1 + falloff)): the kernel \
             and the motion are unchanged; only the PV resistance rises"
        } else {
            "the kernel change (eq. 8.14-8.20) is baked into the lung's kernel by `lungdyn scene \
             prepare`/`demo`/`scene run`; `scene run` reports the centre's motion"
        },
    }))
}

fn closed(
    c: &lung_model::disease::closed::ClosedPneumothorax,
    normal: &NormalBreathing,
    lungs: &[LungBaseline],
) -> anyhow::Result<Value> {
    let plan = c.plan(normal, lungs)?;
    let per_lung: Vec<Value> = plan
        .lungs
        .iter()
        .map(|l| {
            json!({
                "side": l.side.name(),
                "pneumothorax_index": l.index,
                "dV": r3(l.dv),
                "drop_mm": l.drop.map(|d| r3(d.drop_mm)),
                "drop_clamped": l.drop.map(|d| d.clamped),
                "base_volume_ml": r3(l.state.base_volume_ml),
                "tidal_volume_ml": r3(l.state.tidal_ml),
                "held_ml": l.state.held_ml.map(r3),
                "offset_mm": l.state.offset_mm.map(r3),
                "base_lift_mm": r3(l.base_lift_mm),
            })
        })
        .collect();
    Ok(json!({
        "breaths_per_min": r3(plan.times.breaths_per_min()),
        "inhale_s": r3(plan.times.new_inhale_s),
        "exhale_s": r3(plan.times.new_exhale_s),
        "phase_clamped": plan.times.inhale_clamped || plan.times.exhale_clamped,
        "lungs": per_lung,
    }))
}

fn tension(
    params: lung_model::disease::tension::TensionParams,
    onset_s: f64,
    events: &[lung_model::scene_disease::TimedEvent],
    normal: &NormalBreathing,
    lungs: &[LungBaseline],
    cycles: u32,
) -> anyhow::Result<Value> {
    let affected = *lungs
        .iter()
        .find(|l| l.side == params.side)
        .context("the affected lung is not simulated")?;
    let other = lungs.iter().find(|l| l.side != params.side).copied();
    let mut t = Tension::new(params, normal.timing, normal.boundary, affected, other)?;
    let tick_hz = normal.timing.tick_hz;
    let cycle_ticks = |timing: &lung_model::pv::Timing| -> anyhow::Result<u64> {
        let (i, e) = timing.phase_ticks()?;
        Ok(i as u64 + e as u64)
    };
    // Normal cycles until the onset, then the course; interventions in time order with the
    // engine's rule (`engine::runtime::disease`): one arriving at tick T with S(k-1) < T <= S(k)
    // (cycle starts) is applied when cycle k + 1 is prepared, so it shows from cycle k + 1.
    let mut tick = 0u64;
    let onset_tick = (onset_s * tick_hz).round() as u64;
    let normal_cycle = cycle_ticks(&normal.timing)?;
    let mut normal_cycles = 0u64;
    while tick < onset_tick {
        tick += normal_cycle;
        normal_cycles += 1;
    }
    let mut pending: Vec<_> = events.to_vec();
    pending.sort_by(|a, b| a.at_s.total_cmp(&b.at_s));
    let mut pending = pending.into_iter().peekable();
    let mut course = Vec::new();
    let mut records = Vec::new();
    let mut prev_start: Option<u64> = None;
    let mut cur_ticks = normal_cycle;
    for _ in 0..cycles {
        while let (Some(e), Some(prev)) = (pending.peek(), prev_start) {
            let at = e.tick(tick_hz);
            if at > prev {
                break;
            }
            let r = t.intervene(e.kind, e.side, at);
            records.push(json!({
                "tick": r.tick,
                "cycle": r.cycle,
                "kind": r.kind.name(),
                "side": r.side.name(),
                "outcome": match r.outcome {
                    Outcome::Applied => "applied".to_string(),
                    Outcome::WrongSide => "wrong side: no effect".to_string(),
                    Outcome::AlreadyApplied => "already applied".to_string(),
                    Outcome::NoEffect(why) => format!("no effect: {why}"),
                },
            }));
            pending.next();
        }
        let c = t.advance();
        let affected_state = c.affected;
        course.push(json!({
            "cycle": c.cycle,
            "start_tick": tick,
            "pleural_air_ml": r3(c.pleural_air_ml),
            "dV": r3(c.dv),
            "drop_mm": r3(c.drop.drop_mm),
            "shift_mm": r3(c.shift_mm),
            "breaths_per_min": r3(c.times.breaths_per_min()),
            "affected_tidal_ml": r3(affected_state.tidal_ml),
            "other_tidal_ml": c.unaffected.map(|u| r3(u.tidal_ml)),
            "svc_closed": c.svc_closed,
            "arrest": c.arrest,
        }));
        prev_start = Some(tick);
        // A held lung (arrest) keeps the cycle length it had, as in the engine.
        if affected_state.held_ml.is_none() {
            cur_ticks = cycle_ticks(&c.timing).unwrap_or(cur_ticks);
        }
        tick += cur_ticks;
        if c.arrest && pending.peek().is_none() {
            break;
        }
    }
    let last = course.last().cloned().unwrap_or(Value::Null);
    Ok(json!({
        "side": params.side.name(),
        "onset_s": onset_s,
        "normal_cycles_before_onset": normal_cycles,
        "v1_max_ml": r3(t.v1_max_ml()),
        "v2_max_ml": r3(t.v2_max_ml()),
        "shift_mm_per_ml": t.shift_mm_per_ml(),
        "cycles_to_arrest": t.first_arrest(),
        "events": records,
        "final": last,
        "course": course,
    }))
}

/// The report as text.
pub fn text(v: &Value) -> String {
    let mut s = format!(
        "{}: valid — lungs {}, mode {}, PV {} (FRC {} ml, TV {} ml, {} breaths/min)\n",
        v["scene"].as_str().unwrap_or(""),
        v["lungs"],
        v["mode"].as_str().unwrap_or(""),
        v["pv"]["preset"].as_str().unwrap_or(""),
        v["pv"]["frc_ml"],
        v["pv"]["tidal_volume_ml"],
        v["pv"]["breaths_per_min"]
    );
    let c = &v["render"]["calibration"];
    s += &match c["file"].as_str() {
        Some(f) => format!(
            "calibration: {f} (model -> patient reference: {:.2} deg, translation {} mm)\n",
            c["rotation_deg"].as_f64().unwrap_or(0.0),
            c["translation_mm"]
        ),
        None => "calibration: none (the lungs at the renderer's fixed offset from the patient reference)\n".into(),
    };
    let h = &v["render"]["hmd"];
    s += &match h["file"].as_str() {
        Some(f) => format!(
            "HMD optics: {f} ({} x {} px per eye, IPD {} mm, near {} mm, far {} mm)\n",
            h["width_px"], h["height_px"], h["ipd_mm"], h["near_mm"], h["far_mm"]
        ),
        None => {
            "HMD optics: none (the scene's [render] ipd_mm, fov_y_deg, width and height)\n".into()
        }
    };
    let d = &v["disease"];
    if d.is_null() {
        s += "no disease state: normal breathing\n";
        return s;
    }
    s += &format!(
        "disease: {}{}\n",
        d["kind"].as_str().unwrap_or(""),
        if d["engine_applies_it"].as_bool() == Some(true) {
            " (run by `lungdyn demo --scene FILE`)"
        } else {
            " (not run by the engine yet: `demo`/`engine` refuse this scene)"
        }
    );
    if let Some(lungs) = d["lungs"].as_array() {
        s += &format!(
            "  breathing {} /min (inhale {} s, exhale {} s)\n",
            d["breaths_per_min"], d["inhale_s"], d["exhale_s"]
        );
        for l in lungs {
            if l["pneumothorax_index"].is_null() {
                s += &format!(
                    "  {} lung: unaffected, tidal {} ml, base volume {} ml\n",
                    l["side"].as_str().unwrap_or(""),
                    l["tidal_volume_ml"],
                    l["base_volume_ml"]
                );
                continue;
            }
            s += &format!(
                "  {} lung: I = {}, dV = {}, drop {} mm, tidal {} ml, base volume {} ml\n",
                l["side"].as_str().unwrap_or(""),
                l["pneumothorax_index"],
                l["dV"],
                l["drop_mm"],
                l["tidal_volume_ml"],
                l["base_volume_ml"]
            );
        }
    }
    if d.get("course").is_some() {
        s += &format!(
            "  {} side: V1max {} ml, V2max {} ml; {}; {} cycles followed\n",
            d["side"].as_str().unwrap_or(""),
            d["v1_max_ml"],
            d["v2_max_ml"],
            match d["cycles_to_arrest"].as_u64() {
                Some(c) => format!("arrest at cycle {c}"),
                None => "no arrest".to_string(),
            },
            d["course"].as_array().map_or(0, |c| c.len())
        );
        s += &event_lines(d);
        let f = &d["final"];
        s += &format!(
            "  last cycle {}: pleural air {} ml, dV {}, mediastinal shift {} mm, {} /min{}\n",
            f["cycle"],
            f["pleural_air_ml"],
            f["dV"],
            f["shift_mm"],
            f["breaths_per_min"],
            if f["arrest"].as_bool() == Some(true) {
                ", ARREST"
            } else {
                ""
            }
        );
    }
    if let Some(n) = d["note"].as_str() {
        s += &format!("  {n}\n");
    }
    s
}

/// One line per intervention in a report's `events` (tick, cycle, kind, side, outcome).
fn event_lines(d: &Value) -> String {
    let mut s = String::new();
    for e in d["events"].as_array().into_iter().flatten() {
        s += &format!(
            "  event at tick {} (cycle {}): {} {} — {}\n",
            e["tick"],
            e["cycle"],
            e["kind"].as_str().unwrap_or(""),
            e["side"].as_str().unwrap_or(""),
            e["outcome"].as_str().unwrap_or("")
        );
    }
    s
}

/// Options of `lungdyn scene run`.
#[derive(Debug, Clone, clap::Args)]
pub struct RunArgs {
    /// Scene file (TOML).
    pub file: PathBuf,
    /// Simulated seconds (the engine's tick function, as fast as it runs: no processes, no GPU).
    #[arg(long, default_value_t = 60.0)]
    pub seconds: f64,
    /// Folder for the kernels the scene lacks (baked once, reused) and, for a tumour, the centre's
    /// trajectory over the last complete breath (`tumour_trajectory.csv`).
    #[arg(long, default_value = "out")]
    pub out: PathBuf,
    /// Print one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

/// One tick of the tumour centre's track: tick, the lung's cycle, its volume (ml), the centre (mm)
/// and the same centre in the lung without the tumour (mm).
type TrackRow = (u64, u32, f64, [f64; 3], [f64; 3]);

/// A tumour centre followed through the run (the radiotherapy planner's output).
struct TumourFollow {
    slot: usize,
    meta: lung_model::disease::tumour::TumourMeta,
    mode: lung_model::deform::modes::DeformMode,
    /// `(tick, cycle, volume ml, position mm, tumour-free position mm)` of the breath in progress.
    current: Vec<TrackRow>,
    last: Vec<TrackRow>,
    cycle: u32,
    bad: u64,
}

impl TumourFollow {
    fn new(scene: &Scene) -> anyhow::Result<Option<Self>> {
        let Some(t) = scene.tumour() else {
            return Ok(None);
        };
        let kernel = scene.lung_kernel(t.side)?;
        let meta = kernel.meta().tumour.clone().with_context(|| {
            format!(
                "{}: the kernel has no tumour record (baked before lungdyn recorded it); bake it again",
                scene.lungs.kernels.get(t.side).map_or_else(String::new, |p| p.display().to_string())
            )
        })?;
        Ok(Some(Self {
            slot: t.side.index(),
            meta,
            mode: scene.lungs.mode,
            current: Vec::new(),
            last: Vec::new(),
            cycle: 0,
            bad: 0,
        }))
    }

    fn record(&mut self, tick: u64, f: &ipc_types::EngineFrame) {
        let l = &f.lungs[self.slot];
        if !l.is_active() {
            return;
        }
        let n = (l.coeff_count as usize).min(ipc_types::MAX_COEFFS);
        let Some(d) = self.meta.displacement_mm(self.mode, &l.coeffs[..n]) else {
            self.bad += 1;
            return;
        };
        let (s, c) = (l.deform_scale as f64, l.collapse as f64);
        let (h, o) = (l.hilum_mm.map(|v| v as f64), l.offset_mm.map(|v| v as f64));
        let p = self.meta.position_mm(d, s, c, h, o);
        let q = self
            .meta
            .position_mm(self.meta.normal_precomputed_mm, s, c, h, o);
        if !p.iter().all(|v| v.is_finite()) {
            self.bad += 1;
            return;
        }
        if l.cycle != self.cycle {
            self.last = std::mem::take(&mut self.current);
            self.cycle = l.cycle;
        }
        self.current.push((tick, l.cycle, l.volume_ml as f64, p, q));
    }

    /// Motion amplitude per axis (max − min) over the last complete breath (the breath in progress
    /// when none completed), mm: the tumour's and the tumour-free centre's.
    fn amplitudes(&self) -> ([f64; 3], [f64; 3]) {
        let rows = if self.last.is_empty() {
            &self.current
        } else {
            &self.last
        };
        let range = |pick: &dyn Fn(&TrackRow) -> [f64; 3]| {
            [0, 1, 2].map(|a| {
                let (lo, hi) = rows
                    .iter()
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), r| {
                        (l.min(pick(r)[a]), h.max(pick(r)[a]))
                    });
                if lo.is_finite() {
                    r3(hi - lo)
                } else {
                    0.0
                }
            })
        };
        (range(&|r| r.3), range(&|r| r.4))
    }

    /// The last complete breath as CSV, written atomically to `path`.
    fn write_csv(&self, path: &std::path::Path, tick_hz: f64) -> anyhow::Result<()> {
        let rows = if self.last.is_empty() {
            &self.current
        } else {
            &self.last
        };
        lung_model::mesh::io::write_atomically(path, |w| {
            use std::io::Write;
            writeln!(
                w,
                "# tumour centre over one breath, body frame mm (+X left, +Y anterior, +Z superior); \
                 normal_* = the same centre in the lung without the tumour"
            )?;
            writeln!(w, "tick,time_s,cycle,volume_ml,x_mm,y_mm,z_mm,normal_x_mm,normal_y_mm,normal_z_mm")?;
            for (tick, cycle, v, p, q) in rows {
                writeln!(
                    w,
                    "{tick},{:.6},{cycle},{v:.3},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4}",
                    *tick as f64 / tick_hz,
                    p[0], p[1], p[2], q[0], q[1], q[2]
                )?;
            }
            Ok(())
        })
        .with_context(|| format!("cannot write {}", path.display()))?;
        Ok(())
    }
}

/// Run `args.file` through the engine's tick function for `--seconds` of simulated time (fixed
/// supine patient, the scene's timed interventions) and report per lung what the renderer would
/// draw, the disease state's course and how often each stage of the tick did work.
pub fn run_scene(args: &RunArgs) -> anyhow::Result<Value> {
    let s = args.seconds;
    if !(s.is_finite() && s > 0.0 && s <= 24.0 * 3600.0) {
        anyhow::bail!(
            "--seconds {} must be a positive number of seconds, at most 86400 (one day of simulated time)",
            lung_model::plausible::compact(s)
        );
    }
    let scene = Scene::load(&args.file)?;
    let origin = args.file.display().to_string();
    let prepared = crate::prepare::prepare(scene, &args.out.join("kernels"))?;
    let scene = prepared.scene;
    let mut core = engine::runtime::EngineCore::new(&scene)?;
    let mut follow = TumourFollow::new(&scene)?;
    let ticks = (s * scene.engine.tick_hz).round().max(1.0) as u64;
    let mut f = ipc_types::EngineFrame::default();
    let n = ipc_types::NUM_LUNGS;
    let (mut vmin, mut vmax) = (vec![f64::INFINITY; n], vec![f64::NEG_INFINITY; n]);
    // The last complete breath of each lung: its volume range and length.
    let mut cur: Vec<(f64, f64, u64)> = vec![(f64::INFINITY, f64::NEG_INFINITY, 0); n];
    let mut last_breath: Vec<Option<(f64, f64, u64)>> = vec![None; n];
    let mut last_cycle = vec![0u32; n];
    let mut started = vec![0u64; n];
    let mut non_finite = 0u64;
    // A fixed patient in the scene's posture (the synthetic source without drift): the headless run
    // has no tracker, and a patient who does not move costs one orientation evaluation per lung.
    let posture =
        tracker_bridge::synthetic::Posture::parse(scene.tracker.posture.name()).unwrap_or_default();
    let patient = tracker_bridge::synthetic::Synthetic {
        rate_hz: scene.engine.tick_hz,
        drift_deg: 0.0,
        posture,
        ..Default::default()
    };
    for tick in 0..ticks {
        let mut input = patient.frame(tick, 0);
        // The patient's pose only: its quaternion is constant, so is gravity.
        input.tools[ipc_types::TOOL_PATIENT].pose.translation_mm =
            tracker_bridge::synthetic::STERNUM_MM.to_array();
        core.step(tick, Some(&input), &mut f);
        if let Some(t) = &mut follow {
            t.record(tick, &f);
        }
        for (k, l) in f.lungs.iter().enumerate() {
            if !l.is_active() {
                continue;
            }
            let v = l.volume_ml as f64;
            if !(v.is_finite() && l.deform_scale.is_finite()) {
                non_finite += 1;
            }
            vmin[k] = vmin[k].min(v);
            vmax[k] = vmax[k].max(v);
            if l.cycle != last_cycle[k] {
                last_breath[k] = Some((cur[k].0, cur[k].1, tick - started[k]));
                cur[k] = (f64::INFINITY, f64::NEG_INFINITY, 0);
                started[k] = tick;
                last_cycle[k] = l.cycle;
            }
            cur[k].0 = cur[k].0.min(v);
            cur[k].1 = cur[k].1.max(v);
        }
        core.prepare_ahead()?;
    }
    let hz = scene.engine.tick_hz;
    let mut lungs = Vec::new();
    for &side in &scene.lungs.sides {
        let k = side.index();
        let l = &f.lungs[k];
        let (tidal, bpm) = match last_breath[k] {
            Some((lo, hi, len)) if len > 0 => (hi - lo, 60.0 * hz / len as f64),
            _ => (vmax[k] - vmin[k], f64::NAN),
        };
        lungs.push(json!({
            "side": side.name(),
            "volume_min_ml": r3(vmin[k]),
            "volume_max_ml": r3(vmax[k]),
            "tidal_volume_ml": r3(tidal),
            "breaths_per_min": if bpm.is_finite() { json!(r3(bpm)) } else { Value::Null },
            "offset_mm": l.offset_mm.map(|v| r3(v as f64)),
            "collapse": r3(l.collapse as f64),
            "held": l.flags & ipc_types::lung_flags::HELD != 0,
            // The mode's coefficients at the end (force weights for basis/direct): how gravity in
            // this posture shapes the breath.
            "coefficients": l.coeffs[..(l.coeff_count as usize).min(ipc_types::MAX_COEFFS)]
                .iter()
                .map(|&c| r3(c as f64))
                .collect::<Vec<_>>(),
            "cycles": l.cycle,
        }));
    }
    let mut out = json!({
        "scene": origin,
        "posture": scene.tracker.posture.name(),
        "seconds": s,
        "ticks": ticks,
        "mode": format!("{:?}", scene.lungs.mode).to_lowercase(),
        "lungs": lungs,
        "non_finite_frames": non_finite,
        "stage_counts": core.stage_counts(),
        "kernels": prepared.kernels.iter().map(|k| k.path.clone()).collect::<Vec<_>>(),
    });
    if let Some(d) = &scene.disease {
        let mut disease = json!({ "kind": d.kind.name() });
        if let Some(engine::runtime::disease::DiseaseRun::Tension(run)) = core.disease() {
            disease["cycles_run"] = json!(run.cycles_run);
            disease["first_arrest_cycle"] = json!(run.first_arrest);
            disease["events"] = run
                .events
                .iter()
                .map(|e| {
                    json!({
                        "tick": e.tick,
                        "cycle": e.cycle,
                        "kind": e.kind.name(),
                        "side": e.side.name(),
                        "outcome": format!("{:?}", e.outcome),
                    })
                })
                .collect();
        }
        if let (Some(engine::runtime::disease::DiseaseRun::Tumour(run)), Some(t)) =
            (core.disease(), &follow)
        {
            let (amp, normal_amp) = t.amplitudes();
            let csv = args.out.join("tumour_trajectory.csv");
            t.write_csv(&csv, hz)?;
            let m = &t.meta;
            disease["tumour"] = json!({
                "side": run.side.name(),
                "centre_mm": m.centre_mm.map(r3),
                "volume_ml": r3(m.volume_ml),
                "vertices_affected": m.vertices_affected,
                "kernel_entries_changed": m.entries_changed,
                "kernel_entries_clamped": m.entries_clamped,
                "affected_motion_change_percent": { "mean": r3(m.affected_motion_change_percent[0]), "max": r3(m.affected_motion_change_percent[1]) },
                "resistance_x": { "inhale": run.resistance[0].x, "exhale": run.resistance[1].x },
                "trajectory_csv": csv.display().to_string(),
                "trajectory_ticks": if t.last.is_empty() { t.current.len() } else { t.last.len() },
                "non_finite_positions": t.bad,
            });
            disease["tumour_motion_mm"] = json!({ "x": amp[0], "y": amp[1], "z": amp[2] });
            disease["tumour_motion_normal_mm"] =
                json!({ "x": normal_amp[0], "y": normal_amp[1], "z": normal_amp[2] });
        }
        if matches!(
            d.kind,
            lung_model::scene_disease::DiseaseKind::ClosedPneumothorax
                | lung_model::scene_disease::DiseaseKind::BilateralPneumothorax
        ) {
            let sides: Vec<Side> = scene.lungs.sides.clone();
            let spec = d.validate(&sides)?;
            if let DiseaseSpec::Closed(c) = spec {
                let per: Vec<Value> = sides
                    .iter()
                    .filter_map(|&side| {
                        c.index_of(side).map(|i| {
                            let dv =
                                lung_model::disease::volume_fraction_lost(i).unwrap_or(f64::NAN);
                            json!({
                                "side": side.name(),
                                "pneumothorax_index": i,
                                "dV": r3(dv),
                                "drop_mm": r3(lung_model::disease::drop_for_index(i).drop_mm),
                            })
                        })
                    })
                    .collect();
                disease["affected"] = json!(per);
            }
        }
        out["disease"] = disease;
    }
    Ok(out)
}

/// The `scene run` report as text.
pub fn run_text(v: &Value) -> String {
    let mut s = format!(
        "{}: {} s simulated ({} ticks, mode {}, patient {} and still){}\n",
        v["scene"].as_str().unwrap_or(""),
        v["seconds"],
        v["ticks"],
        v["mode"].as_str().unwrap_or(""),
        v["posture"].as_str().unwrap_or(""),
        if v["non_finite_frames"].as_u64() == Some(0) {
            String::new()
        } else {
            format!(", {} NON-FINITE frames", v["non_finite_frames"])
        }
    );
    for l in v["lungs"].as_array().into_iter().flatten() {
        s += &format!(
            "  {} lung: {}–{} ml, last breath {} ml at {} /min, offset {} mm, collapse {}{}\n",
            l["side"].as_str().unwrap_or(""),
            l["volume_min_ml"],
            l["volume_max_ml"],
            l["tidal_volume_ml"],
            l["breaths_per_min"],
            l["offset_mm"],
            l["collapse"],
            if l["held"].as_bool() == Some(true) {
                ", HELD (not breathing)"
            } else {
                ""
            }
        );
    }
    if let Some(d) = v.get("disease") {
        s += &format!("  disease {}", d["kind"].as_str().unwrap_or(""));
        if let Some(c) = d.get("cycles_run") {
            s += &format!(
                ": {} cycles, {}",
                c,
                match d["first_arrest_cycle"].as_u64() {
                    Some(a) => format!("arrest at cycle {a}"),
                    None => "no arrest".to_string(),
                }
            );
        }
        s += "\n";
        if let Some(m) = d.get("tumour_motion_mm") {
            s += &format!(
                "  tumour centre {} mm moves {} / {} / {} mm (x / y / z) over the last breath (without \
                 the tumour: {} / {} / {} mm); trajectory in {}\n",
                d["tumour"]["centre_mm"],
                m["x"],
                m["y"],
                m["z"],
                d["tumour_motion_normal_mm"]["x"],
                d["tumour_motion_normal_mm"]["y"],
                d["tumour_motion_normal_mm"]["z"],
                d["tumour"]["trajectory_csv"].as_str().unwrap_or("")
            );
        }
        s += &event_lines(d);
    }
    s += &format!("  stage counts: {}\n", v["stage_counts"]);
    s
}
