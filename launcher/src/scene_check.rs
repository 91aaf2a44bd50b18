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
use lung_model::disease::ventilated::Ventilator;
use lung_model::disease::{LungBaseline, LungState, NormalBreathing};
use lung_model::mesh::{Side, TriMesh};
use lung_model::scene::Scene;
use lung_model::scene::SceneExt;
use lung_model::scene_disease::DiseaseSceneExt;
use lung_model::scene_disease::DiseaseSpec;
use serde::Serialize;

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
        None => lung_model::mesh::generate::lung_of(scene.lungs.shape, side, scene.lungs.vertices)
            .with_context(|| format!("the built-in {} lung", side.name())),
    }
}

fn r3(v: f64) -> f64 {
    (v * 1000.0).round() / 1000.0
}

/// A value as JSON writes it (numbers, arrays, `null`, objects with sorted keys): the text shows
/// the figures exactly as `--json` does.
fn j<T: Serialize + ?Sized>(v: &T) -> String {
    serde_json::to_value(v).map_or_else(|e| format!("<{e}>"), |v| v.to_string())
}

/// What `lungdyn scene check` reports (`--json` writes it; [`text`] prints it).
#[derive(Debug, Clone, Serialize)]
pub struct CheckReport {
    /// The scene file.
    pub scene: String,
    /// Always true: an invalid scene is an error, not a report.
    pub valid: bool,
    /// The simulated lungs.
    pub lungs: Vec<&'static str>,
    /// Deformation mode.
    pub mode: String,
    /// SH bands.
    pub bands: u32,
    /// The PV model.
    pub pv: PvReport,
    /// The renderer's calibration and HMD optics.
    pub render: RenderReport,
    /// The disease state's report; `null` for normal breathing.
    pub disease: Option<DiseaseReport>,
}

/// The scene's PV model.
#[derive(Debug, Clone, Serialize)]
pub struct PvReport {
    /// Preset name (Table 5.1).
    pub preset: String,
    /// Constants file, if any.
    pub constants: Option<String>,
    /// The recording a `[pv] waveform` scene plays, if any (no PV model is built then).
    pub waveform: Option<String>,
    /// Clean breaths of the recording averaged into the played breath.
    pub waveform_breaths_used: Option<usize>,
    /// What the ventilator of a waveform scene holds fixed, and why (EQUATIONS §4.7).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub waveform_control: Option<lung_model::scene::ControlChoice>,
    /// Functional residual capacity, ml.
    pub frc_ml: f64,
    /// Tidal volume, ml.
    pub tidal_volume_ml: f64,
    /// Breathing rate.
    pub breaths_per_min: f64,
}

/// The renderer's files as the renderer loads them.
#[derive(Debug, Clone, Serialize)]
pub struct RenderReport {
    /// The calibration (`null`: the renderer's fixed offset).
    pub calibration: Option<CalibrationSeen>,
    /// The HMD optics (`null`: the scene's `[render]` values).
    pub hmd: Option<OpticsSeen>,
}

/// A calibration file and what it holds; serialized as `lungdyn register` shows it.
#[derive(Debug, Clone)]
pub struct CalibrationSeen {
    /// Where it was read from.
    pub file: PathBuf,
    /// Its transform.
    pub calibration: tracker_pose::calib::Calibration,
}

impl Serialize for CalibrationSeen {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        crate::rig_json::calibration_json(&self.file, &self.calibration).serialize(s)
    }
}

/// An HMD optics file and what it holds; serialized as `lungdyn hmd check` shows it.
#[derive(Debug, Clone)]
pub struct OpticsSeen {
    /// Where it was read from.
    pub file: PathBuf,
    /// The optics.
    pub optics: tracker_pose::optics::Optics,
}

impl Serialize for OpticsSeen {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        crate::rig_json::optics_json(Some(&self.file), &self.optics).serialize(s)
    }
}

/// A disease state's report: its kind and the model's course.
#[derive(Debug, Clone, Serialize)]
pub struct DiseaseReport {
    /// The `[disease] kind`.
    pub kind: &'static str,
    /// Whether `demo`/`engine` run it (every kind does).
    pub engine_applies_it: bool,
    /// The course runs on a ventilator's recorded breath (`[pv] waveform`): the lungs share the
    /// delivered volume at the recording's rate (EQUATIONS §4.7). Absent otherwise.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub ventilated: bool,
    /// The kind's own figures.
    #[serde(flatten)]
    pub detail: DiseaseDetail,
}

/// The figures of each kind of disease state.
#[derive(Debug, Clone, Serialize)]
#[serde(untagged)]
pub enum DiseaseDetail {
    /// A closed (or bilateral) pneumothorax's plan.
    Closed(ClosedReport),
    /// A tension pneumothorax's course.
    Tension(TensionReport),
    /// A tumour's parameters.
    Tumour(TumourReport),
}

/// A closed pneumothorax's plan (eq. 8.1–8.9).
#[derive(Debug, Clone, Serialize)]
pub struct ClosedReport {
    /// The reading: "clinical" (EQUATIONS §4.6) or "seed".
    pub model: &'static str,
    /// Breathing rate after the change.
    pub breaths_per_min: f64,
    /// Both lungs' tidal volumes times the rate, l/min.
    pub minute_ventilation_l_per_min: f64,
    /// Inhalation, s.
    pub inhale_s: f64,
    /// Exhalation, s.
    pub exhale_s: f64,
    /// Whether a phase was clamped.
    pub phase_clamped: bool,
    /// Each lung.
    pub lungs: Vec<ClosedLung>,
    /// On a ventilated scene: what the ventilator delivers.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub delivery: Option<DeliveryReport>,
}

/// One lung of a closed pneumothorax's plan.
#[derive(Debug, Clone, Serialize)]
pub struct ClosedLung {
    /// Which lung.
    pub side: &'static str,
    /// Pneumothorax index I (`null`: unaffected).
    pub pneumothorax_index: Option<f64>,
    /// Volume fraction lost.
    #[serde(rename = "dV")]
    pub dv: f64,
    /// Base drop, mm.
    pub drop_mm: Option<f64>,
    /// Whether the drop was clamped.
    pub drop_clamped: Option<bool>,
    /// Base volume, ml.
    pub base_volume_ml: f64,
    /// Tidal volume, ml.
    pub tidal_volume_ml: f64,
    /// Volume held (not breathing), ml.
    pub held_ml: Option<f64>,
    /// Rigid offset, mm.
    pub offset_mm: [f64; 3],
    /// Base lift, mm.
    pub base_lift_mm: f64,
}

/// A tension pneumothorax's course (eq. 8.10–8.13).
#[derive(Debug, Clone, Serialize)]
pub struct TensionReport {
    /// The reading: "clinical" (EQUATIONS §4.6) or "seed".
    pub model: &'static str,
    /// The affected side.
    pub side: &'static str,
    /// Onset, s.
    pub onset_s: f64,
    /// Normal breaths before the onset.
    pub normal_cycles_before_onset: u64,
    /// V1max, ml.
    pub v1_max_ml: f64,
    /// V2max, ml.
    pub v2_max_ml: f64,
    /// Mediastinal shift per ml of pleural air beyond V1max (the seed reading's eq. 8.13 on the
    /// collapsed box).
    pub shift_mm_per_ml: f64,
    /// Pleural air at which the shift reaches β and the SVC closes, ml.
    pub svc_closing_air_ml: f64,
    /// Clinical: pleural air at atmospheric pressure (what a needle leaves), ml.
    pub atmospheric_air_ml: Option<f64>,
    /// First cycle in arrest, if any.
    pub cycles_to_arrest: Option<u64>,
    /// The timed interventions, as applied.
    pub events: Vec<EventReport>,
    /// The last cycle followed.
    #[serde(rename = "final")]
    pub last: Option<CycleReport>,
    /// Every cycle followed.
    pub course: Vec<CycleReport>,
}

/// One cycle of a tension pneumothorax's course.
#[derive(Debug, Clone, Serialize)]
pub struct CycleReport {
    /// Cycle since the onset.
    pub cycle: u64,
    /// Its first tick.
    pub start_tick: u64,
    /// Pleural air, ml.
    pub pleural_air_ml: f64,
    /// Volume fraction lost.
    #[serde(rename = "dV")]
    pub dv: f64,
    /// Base drop, mm.
    pub drop_mm: f64,
    /// Mediastinal shift, mm.
    pub shift_mm: f64,
    /// Breathing rate.
    pub breaths_per_min: f64,
    /// The affected lung's tidal volume, ml.
    pub affected_tidal_ml: f64,
    /// The other lung's tidal volume, ml.
    pub other_tidal_ml: Option<f64>,
    /// The other lung's volume at the start of its breath, ml (its FRC volume less what the shifted
    /// mediastinum compresses; EQUATIONS §4.6 (f)).
    pub other_base_volume_ml: Option<f64>,
    /// Both lungs' tidal volumes times the rate, l/min.
    pub minute_ventilation_l_per_min: f64,
    /// Whether the SVC is closed.
    pub svc_closed: bool,
    /// Whether the patient is in arrest.
    pub arrest: bool,
    /// On a ventilated scene: what the ventilator delivered this cycle.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub delivery: Option<DeliveryReport>,
}

/// What a ventilator delivered in one cycle of a course on a recorded breath (EQUATIONS §4.7).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct DeliveryReport {
    /// `"volume"` or `"pressure"`: what the ventilator holds fixed.
    pub control: &'static str,
    /// Volume delivered to the simulated lungs per breath, ml.
    pub delivered_ml: f64,
    /// Against the recorded volume (1: all of it).
    pub delivered_fraction: f64,
    /// The breathing lungs' compliance against the recording's.
    pub compliance_ratio: f64,
    /// Volume control: the pressure limit ended the inspiration before the volume was delivered.
    pub pressure_capped: bool,
}

/// One intervention: when it arrived, from which cycle it shows, what it did.
#[derive(Debug, Clone, Serialize)]
pub struct EventReport {
    /// Engine tick it arrived at.
    pub tick: u64,
    /// First cycle whose state reflects it.
    pub cycle: u64,
    /// The intervention.
    pub kind: ipc_types::Intervention,
    /// The side.
    pub side: &'static str,
    /// What it did.
    pub outcome: String,
}

/// A tumour's parameters and raised resistance, without baking.
#[derive(Debug, Clone, Serialize)]
pub struct TumourReport {
    /// The lung.
    pub side: &'static str,
    /// Centre as the scene gives it (fractions of the lung's box).
    pub centre: [f64; 3],
    /// Centre, mm.
    pub centre_mm: [f64; 3],
    /// Semi-axes, mm.
    pub radii_mm: [f64; 3],
    /// Volume, ml.
    pub volume_ml: f64,
    /// Expandability inside.
    pub expandability: f64,
    /// Falloff.
    pub falloff: f64,
    /// Coupling.
    pub coupling: f64,
    /// Eq. 8.21 variant.
    pub phi_variant: String,
    /// Surface vertices with expandability below 1.
    pub surface_vertices_affected: usize,
    /// Raised resistance factors.
    pub resistance_x: InhaleExhale,
    /// What happens to the kernel.
    pub note: &'static str,
}

/// A pair of inhalation and exhalation figures.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct InhaleExhale {
    /// Inhalation.
    pub inhale: f64,
    /// Exhalation.
    pub exhale: f64,
}

/// Validate `args.file` and report.
pub fn run(args: &CheckArgs) -> anyhow::Result<CheckReport> {
    if !(1..=MAX_CYCLES).contains(&args.cycles) {
        anyhow::bail!("--cycles {} must be within 1..{MAX_CYCLES}", args.cycles);
    }
    let scene = Scene::load(&args.file)?;
    let origin = args.file.display().to_string();
    // The kernels it names, checked as `scene prepare` and the processes check them: a scene this
    // calls valid must not be refused at the launch.
    for &side in &scene.lungs.sides {
        if scene.lungs.kernels.get(side).is_some() {
            crate::prepare::check_named_kernel(&scene, side)
                .with_context(|| format!("scene {origin}"))?;
        }
    }
    let (inhale, exhale, boundary) = scene
        .pv_model()
        .with_context(|| format!("scene {origin}"))?;
    // The renderer's calibration and HMD optics files, loaded as the renderer loads them.
    let rig = renderer::camera::RigFiles::load(&scene.render, None, None)
        .with_context(|| format!("scene {origin}"))?;
    let render = RenderReport {
        calibration: rig
            .calibration
            .map(|(file, _, calibration)| CalibrationSeen { file, calibration }),
        hmd: rig
            .optics
            .map(|(file, _, optics)| OpticsSeen { file, optics }),
    };
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
    let mut out = CheckReport {
        scene: origin,
        valid: true,
        lungs: scene.lungs.sides.iter().map(|s| s.name()).collect(),
        mode: format!("{:?}", scene.lungs.mode).to_lowercase(),
        bands: scene.lungs.bands,
        pv: PvReport {
            preset: scene.pv.preset.clone(),
            constants: scene.pv.constants.as_ref().map(|p| p.display().to_string()),
            waveform: scene.pv.waveform.as_ref().map(|p| p.display().to_string()),
            waveform_breaths_used: waveform.as_ref().map(|w| w.breaths_used),
            waveform_control: waveform
                .as_ref()
                .map(|w| control_choice(w, &scene))
                .transpose()?,
            frc_ml,
            tidal_volume_ml: (tv_ml * 1000.0).round() / 1000.0,
            breaths_per_min: timing.breaths_per_min,
        },
        render,
        disease: None,
    };
    let Some(d) = &scene.disease else {
        return Ok(out);
    };
    let spec = scene
        .disease_spec()?
        .context("a [disease] table without a disease state")?;
    let mut baselines = Vec::new();
    for &side in &scene.lungs.sides {
        let mesh = lung_mesh(&scene, side)?;
        let share = mesh.enclosed_volume_ml() / boundary.frc_ml;
        baselines.push(
            LungBaseline::of(&mesh, side, share)
                .with_context(|| format!("the {} lung's baseline", side.name()))?,
        );
    }
    // On a waveform scene the course runs on the recorded breath (EQUATIONS §4.7).
    let ventilator = scene
        .ventilator(&baselines)
        .with_context(|| format!("scene {}", out.scene))?
        .map(|(v, _)| v);
    let normal = lung_model::disease::ventilated::normal_breathing(
        ventilator.as_ref().map(|v| &v.recorded),
        scene.timing(),
        inhale,
        exhale,
        boundary,
    );
    let ventilated = ventilator.is_some();
    let detail = match &spec {
        DiseaseSpec::Closed(c) => {
            DiseaseDetail::Closed(closed(c, &normal, &baselines, ventilator.as_ref())?)
        }
        DiseaseSpec::Tension {
            params,
            onset_s,
            events,
        } => DiseaseDetail::Tension(tension(
            *params,
            *onset_s,
            events,
            &normal,
            &baselines,
            args.cycles,
            ventilator.as_ref(),
        )?),
        DiseaseSpec::Tumour(t) => DiseaseDetail::Tumour(tumour(t, &scene, &normal, &baselines)?),
    };
    out.disease = Some(DiseaseReport {
        kind: d.kind.name(),
        engine_applies_it: true,
        ventilated,
        detail,
    });
    Ok(out)
}

/// The control mode of a waveform scene's ventilator; a contradiction of the recording is warned
/// about on stderr (the report carries it too).
fn control_choice(
    w: &lung_model::recording::Waveform,
    scene: &Scene,
) -> Result<lung_model::scene::ControlChoice, lung_model::scene::SceneValueError> {
    let c = Scene::waveform_control(w, scene.pv.waveform_control)?;
    if let Some(warning) = &c.warning {
        eprintln!("warning: {warning}");
    }
    Ok(c)
}

/// A tumour's report without baking: where its centre is, that it lies inside the lung, how many
/// surface vertices its expandability reaches, and the raised resistance (eq. 8.9).
fn tumour(
    t: &lung_model::disease::tumour::Tumour,
    scene: &Scene,
    normal: &NormalBreathing,
    lungs: &[LungBaseline],
) -> anyhow::Result<TumourReport> {
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
    Ok(TumourReport {
        side: t.side.name(),
        centre: t.centre,
        centre_mm: centre.map(r3),
        radii_mm: t.radii_mm,
        volume_ml: r3(t.volume_ml()),
        expandability: t.expandability,
        falloff: t.falloff,
        coupling: t.coupling,
        phi_variant: format!("{:?}", t.phi).to_lowercase(),
        surface_vertices_affected: affected,
        resistance_x: InhaleExhale {
            inhale: ri.x,
            exhale: re.x,
        },
        note: if affected == 0 {
            "no surface vertex lies within the tumour's reach (radius x (1 + falloff)): the kernel \
             and the motion are unchanged; only the PV resistance rises"
        } else {
            "the kernel change (eq. 8.14-8.20) is baked into the lung's kernel by `lungdyn scene \
             prepare`/`demo`/`scene run`; `scene run` reports the centre's motion"
        },
    })
}

/// A ventilated course's states: the ventilator's breath shared by the lungs that breathe (EQUATIONS
/// §4.7), as the engine shares it; what was delivered.
fn deliver(
    states: &mut [&mut LungState],
    ventilator: &Ventilator,
) -> anyhow::Result<lung_model::disease::ventilated::Delivery> {
    let mut copy: Vec<LungState> = states.iter().map(|s| **s).collect();
    let (d, _) = ventilator
        .deliver(&mut copy)
        .context("the ventilated breath")?;
    for (s, c) in states.iter_mut().zip(copy) {
        **s = c;
    }
    Ok(d)
}

/// A delivery as the report shows it (figures to 0.001).
fn delivery_report(d: lung_model::disease::ventilated::Delivery) -> DeliveryReport {
    DeliveryReport {
        control: d.control.name(),
        delivered_ml: r3(d.delivered_ml),
        delivered_fraction: r3(d.fraction),
        compliance_ratio: r3(d.compliance_ratio),
        pressure_capped: d.pressure_capped,
    }
}

fn closed(
    c: &lung_model::disease::closed::ClosedPneumothorax,
    normal: &NormalBreathing,
    lungs: &[LungBaseline],
    ventilator: Option<&Ventilator>,
) -> anyhow::Result<ClosedReport> {
    let mut plan = c.plan(normal, lungs)?;
    let mut delivery = None;
    if let Some(v) = ventilator {
        // The ventilator's rate and I:E (the recording's), its breath shared by the lungs.
        let mut states: Vec<&mut LungState> = plan.lungs.iter_mut().map(|l| &mut l.state).collect();
        delivery = Some(delivery_report(deliver(&mut states, v)?));
        plan.times = lung_model::disease::phase_times(&normal.timing, 0.0)?;
    }
    let tidal: f64 = plan.lungs.iter().map(|l| l.state.tidal_ml).sum();
    let lungs = plan
        .lungs
        .iter()
        .map(|l| ClosedLung {
            side: l.side.name(),
            pneumothorax_index: l.index,
            dv: r3(l.dv),
            drop_mm: l.drop.map(|d| r3(d.drop_mm)),
            drop_clamped: l.drop.map(|d| d.clamped),
            base_volume_ml: r3(l.state.base_volume_ml),
            tidal_volume_ml: r3(l.state.tidal_ml),
            held_ml: l.state.held_ml.map(r3),
            offset_mm: l.state.offset_mm.map(r3),
            base_lift_mm: r3(l.base_lift_mm),
        })
        .collect();
    Ok(ClosedReport {
        model: c.model.name(),
        breaths_per_min: r3(plan.times.breaths_per_min()),
        minute_ventilation_l_per_min: r3(plan.times.breaths_per_min() * tidal / 1000.0),
        inhale_s: r3(plan.times.new_inhale_s),
        exhale_s: r3(plan.times.new_exhale_s),
        phase_clamped: plan.times.inhale_clamped || plan.times.exhale_clamped,
        lungs,
        delivery,
    })
}

fn tension(
    params: lung_model::disease::tension::TensionParams,
    onset_s: f64,
    events: &[lung_model::scene_disease::TimedEvent],
    normal: &NormalBreathing,
    lungs: &[LungBaseline],
    cycles: u32,
    ventilator: Option<&Ventilator>,
) -> anyhow::Result<TensionReport> {
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
            records.push(EventReport {
                tick: r.tick,
                cycle: r.cycle,
                kind: r.kind,
                side: r.side.name(),
                outcome: match r.outcome {
                    Outcome::Applied => "applied".to_string(),
                    Outcome::WrongSide => "wrong side: no effect".to_string(),
                    Outcome::AlreadyApplied => "already applied".to_string(),
                    Outcome::NoEffect(why) => format!("no effect: {why}"),
                },
            });
            pending.next();
        }
        let mut c = t.advance();
        let mut delivery = None;
        if let Some(v) = ventilator {
            // The ventilator's rate (the recording's), its breath shared by the lungs that breathe.
            let mut states: Vec<&mut LungState> = std::iter::once(&mut c.affected)
                .chain(c.unaffected.as_mut())
                .collect();
            delivery = Some(delivery_report(deliver(&mut states, v)?));
            c.times = lung_model::disease::phase_times(&normal.timing, 0.0)?;
            c.timing = normal.timing;
        }
        let affected_state = c.affected;
        let tidal = affected_state.tidal_ml + c.unaffected.map_or(0.0, |u| u.tidal_ml);
        course.push(CycleReport {
            cycle: c.cycle,
            start_tick: tick,
            pleural_air_ml: r3(c.pleural_air_ml),
            dv: r3(c.dv),
            drop_mm: r3(c.drop.drop_mm),
            shift_mm: r3(c.shift_mm),
            breaths_per_min: r3(c.times.breaths_per_min()),
            affected_tidal_ml: r3(affected_state.tidal_ml),
            other_tidal_ml: c.unaffected.map(|u| r3(u.tidal_ml)),
            other_base_volume_ml: c.unaffected.map(|u| r3(u.base_volume_ml)),
            minute_ventilation_l_per_min: r3(c.times.breaths_per_min() * tidal / 1000.0),
            svc_closed: c.svc_closed,
            arrest: c.arrest,
            delivery,
        });
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
    Ok(TensionReport {
        model: params.model.name(),
        side: params.side.name(),
        onset_s,
        normal_cycles_before_onset: normal_cycles,
        v1_max_ml: r3(t.v1_max_ml()),
        v2_max_ml: r3(t.v2_max_ml()),
        shift_mm_per_ml: t.shift_mm_per_ml(),
        svc_closing_air_ml: r3(t.svc_closing_air_ml()),
        atmospheric_air_ml: (params.model == lung_model::disease::CourseModel::Clinical)
            .then(|| r3(t.atmospheric_air_ml())),
        cycles_to_arrest: t.first_arrest(),
        events: records,
        last: course.last().cloned(),
        course,
    })
}

/// The report as text.
pub fn text(r: &CheckReport) -> String {
    let mut s = format!(
        "{}: valid — lungs {}, mode {}, PV {} (FRC {} ml, TV {} ml, {} breaths/min)\n",
        r.scene,
        j(&r.lungs),
        r.mode,
        r.pv.preset,
        j(&r.pv.frc_ml),
        j(&r.pv.tidal_volume_ml),
        j(&r.pv.breaths_per_min)
    );
    s += &match &r.render.calibration {
        Some(c) => {
            let t = c.calibration.translation_mm;
            format!(
                "calibration: {} (model -> patient reference: {:.2} deg, translation {} mm)\n",
                c.file.display(),
                c.calibration.rotation.angle().to_degrees(),
                j(&[t.x, t.y, t.z])
            )
        }
        None => "calibration: none (the lungs at the renderer's fixed offset from the patient reference)\n".into(),
    };
    s += &match &r.render.hmd {
        Some(h) => {
            let o = &h.optics;
            format!(
                "HMD optics: {} ({} x {} px per eye, IPD {} mm, near {} mm, far {} mm)\n",
                h.file.display(),
                j(&o.width_px),
                j(&o.height_px),
                j(&o.ipd_mm),
                j(&o.near_mm),
                j(&o.far_mm)
            )
        }
        None => {
            "HMD optics: none (the scene's [render] ipd_mm, fov_y_deg, width and height)\n".into()
        }
    };
    if let Some(c) = &r.pv.waveform_control {
        s += &format!(
            "ventilator: {} control (set by the {}; the recording: {})\n",
            c.mode.name(),
            c.set_by,
            c.recording
        );
    }
    let Some(d) = &r.disease else {
        s += "no disease state: normal breathing\n";
        return s;
    };
    s += &format!(
        "disease: {}{}\n",
        d.kind,
        if d.engine_applies_it {
            " (run by `lungdyn demo --scene FILE`)"
        } else {
            " (not run by the engine yet: `demo`/`engine` refuse this scene)"
        }
    );
    if d.ventilated {
        s += "  ventilated: the ventilator gives the recorded breath at its rate (volume control: \
              its volume, up to the pressure limit; pressure control: its pressure, the volume \
              following the compliance); the lungs that breathe share it by compliance \
              (EQUATIONS §4.7)\n";
    }
    match &d.detail {
        DiseaseDetail::Closed(c) => {
            s += &format!(
                "  model {}: breathing {} /min (inhale {} s, exhale {} s{}), minute ventilation {} l/min\n",
                c.model,
                j(&c.breaths_per_min),
                j(&c.inhale_s),
                j(&c.exhale_s),
                if c.phase_clamped { ", rate capped" } else { "" },
                j(&c.minute_ventilation_l_per_min)
            );
            if let Some(d) = &c.delivery {
                s += &delivery_line(d);
            }
            for l in &c.lungs {
                let Some(index) = l.pneumothorax_index else {
                    s += &format!(
                        "  {} lung: unaffected, tidal {} ml, base volume {} ml\n",
                        l.side,
                        j(&l.tidal_volume_ml),
                        j(&l.base_volume_ml)
                    );
                    continue;
                };
                s += &format!(
                    "  {} lung: I = {}, dV = {}, drop {} mm, tidal {} ml, base volume {} ml\n",
                    l.side,
                    j(&index),
                    j(&l.dv),
                    j(&l.drop_mm),
                    j(&l.tidal_volume_ml),
                    j(&l.base_volume_ml)
                );
            }
        }
        DiseaseDetail::Tension(t) => {
            s += &format!(
                "  {} side, model {}: V1max {} ml, V2max {} ml, SVC closes at {} ml of pleural air{}; {}; {} cycles followed\n",
                t.side,
                t.model,
                j(&t.v1_max_ml),
                j(&t.v2_max_ml),
                j(&t.svc_closing_air_ml),
                match t.atmospheric_air_ml {
                    Some(a) => format!(", a needle leaves {} ml", j(&a)),
                    None => String::new(),
                },
                match t.cycles_to_arrest {
                    Some(c) => format!("arrest at cycle {c}"),
                    None => "no arrest".to_string(),
                },
                t.course.len()
            );
            s += &course_lines(t);
            if let Some(f) = &t.last {
                s += &format!(
                    "  last cycle {}: pleural air {} ml, dV {}, mediastinal shift {} mm, {} /min{}\n",
                    f.cycle,
                    j(&f.pleural_air_ml),
                    j(&f.dv),
                    j(&f.shift_mm),
                    j(&f.breaths_per_min),
                    if f.arrest { ", ARREST" } else { "" }
                );
            }
        }
        DiseaseDetail::Tumour(t) => s += &format!("  {}\n", t.note),
    }
    s
}

/// A tension pneumothorax's course in a few lines: the first cycle with air, the first with a
/// mediastinal shift, the SVC's closure, and each intervention with the course one and three cycles
/// after it shows (the relief a trainee should see).
fn course_lines(t: &TensionReport) -> String {
    let line = |what: &str, c: &CycleReport| {
        format!(
            "  {what} cycle {}: pleural air {} ml, dV {}, shift {} mm, tidal {} + {} ml at {} /min ({} l/min){}\n",
            c.cycle,
            j(&c.pleural_air_ml),
            j(&c.dv),
            j(&c.shift_mm),
            j(&c.affected_tidal_ml),
            j(&c.other_tidal_ml.unwrap_or(0.0)),
            j(&c.breaths_per_min),
            j(&c.minute_ventilation_l_per_min),
            if c.arrest {
                ", ARREST"
            } else if c.svc_closed {
                ", SVC closed"
            } else {
                ""
            }
        ) + &c.delivery.as_ref().map_or_else(String::new, |d| format!("  {}", delivery_line(d)))
    };
    let mut s = String::new();
    let first = |f: &dyn Fn(&CycleReport) -> bool| t.course.iter().find(|c| f(c));
    if let Some(c) = t.course.first() {
        s += &line("onset", c);
    }
    if let Some(c) = first(&|c| c.pleural_air_ml > 0.0) {
        s += &line("first air", c);
    }
    if let Some(c) = first(&|c| c.shift_mm > 0.0) {
        s += &line("first shift", c);
    }
    if let Some(c) = first(&|c| c.svc_closed) {
        s += &line("SVC closes", c);
    }
    for e in &t.events {
        s += &event_lines(std::slice::from_ref(e));
        for k in [0, 2] {
            if let Some(c) = t.course.iter().find(|c| c.cycle == e.cycle + k) {
                s += &line(&format!("  {} cycle(s) on:", k + 1), c);
            }
        }
    }
    s
}

/// What a ventilator delivered, in a line.
fn delivery_line(d: &DeliveryReport) -> String {
    format!(
        "  {} control: {} ml delivered ({} of the recorded volume; compliance {} of the recording's){}\n",
        d.control,
        j(&d.delivered_ml),
        j(&d.delivered_fraction),
        j(&d.compliance_ratio),
        if d.pressure_capped {
            ", the pressure limit ends the inspiration"
        } else {
            ""
        }
    )
}

/// One line per intervention (tick, cycle, kind, side, outcome).
fn event_lines(events: &[EventReport]) -> String {
    let mut s = String::new();
    for e in events {
        s += &format!(
            "  event at tick {} (cycle {}): {} {} — {}\n",
            e.tick, e.cycle, e.kind, e.side, e.outcome
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
    meta: lung_model::kernel::TumourMeta,
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
        outfile::write_atomically(path, |w| {
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

/// The headless runs' tracker: a fixed patient in the scene's posture (the synthetic source without
/// drift). The headless run has no tracker, and a patient who does not move costs one orientation
/// evaluation per lung.
pub fn still_patient(scene: &Scene) -> impl FnMut(u64) -> ipc_types::TrackerFrame {
    let patient = tracker_bridge::synthetic::Synthetic {
        rate_hz: scene.engine.tick_hz,
        drift_deg: 0.0,
        posture: scene.tracker.posture,
        ..Default::default()
    };
    move |tick| {
        let mut input = patient.frame(tick, 0);
        // The patient's pose only: its quaternion is constant, so is gravity.
        input.tools[ipc_types::TOOL_PATIENT].pose.translation_mm =
            tracker_bridge::synthetic::STERNUM_MM.to_array();
        input
    }
}

/// Run `args.file` through the engine's tick function for `--seconds` of simulated time (fixed
/// supine patient, the scene's timed interventions) and report per lung what the renderer would
/// draw, the disease state's course and how often each stage of the tick did work.
pub fn run_scene(args: &RunArgs) -> anyhow::Result<RunReport> {
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
    let mut follow = TumourFollow::new(&scene)?;
    let ticks = (s * scene.engine.tick_hz).round().max(1.0) as u64;
    let run = engine::headless::run(&scene, ticks, &mut still_patient(&scene), &mut |tick, f| {
        if let Some(t) = &mut follow {
            t.record(tick, f);
        }
    })?;
    let (core, f) = (&run.core, &run.last);
    let hz = scene.engine.tick_hz;
    let mut lungs = Vec::new();
    for &side in &scene.lungs.sides {
        let k = side.index();
        let l = &f.lungs[k];
        let summary = &run.lungs[k];
        let (tidal, bpm) = summary.tidal_and_rate(hz);
        lungs.push(RunLung {
            side: side.name(),
            volume_min_ml: r3(summary.volume_range_ml.0),
            volume_max_ml: r3(summary.volume_range_ml.1),
            tidal_volume_ml: r3(tidal),
            breaths_per_min: bpm.map(r3),
            offset_mm: l.offset_mm.map(|v| r3(v as f64)),
            collapse: r3(l.collapse as f64),
            held: l.flags & ipc_types::lung_flags::HELD != 0,
            // The mode's coefficients at the end (force weights for basis/direct): how gravity in
            // this posture shapes the breath.
            coefficients: l.coeffs[..(l.coeff_count as usize).min(ipc_types::MAX_COEFFS)]
                .iter()
                .map(|&c| r3(c as f64))
                .collect(),
            cycles: l.cycle,
        });
    }
    let non_finite = run.non_finite_frames;
    let mut out = RunReport {
        scene: origin,
        posture: scene.tracker.posture.name(),
        seconds: s,
        ticks,
        mode: format!("{:?}", scene.lungs.mode).to_lowercase(),
        lungs,
        non_finite_frames: non_finite,
        stage_counts: core.stage_counts(),
        kernels: prepared.kernels.iter().map(|k| k.path.clone()).collect(),
        disease: None,
        ventilator: match scene.pv_waveform()? {
            Some(w) => Some(RunVentilator {
                control: control_choice(&w, &scene)?,
                delivery: core.disease().and_then(|d| d.delivery()),
            }),
            None => None,
        },
    };
    out.disease = disease_report(args, &scene, core, follow.as_ref(), hz)?;
    Ok(out)
}

/// The disease state's part of the report: a tension pneumothorax's cycles and events, a tumour's
/// motion (its trajectory written to `--out`), a closed pneumothorax's affected lungs.
fn disease_report(
    args: &RunArgs,
    scene: &Scene,
    core: &engine::runtime::EngineCore,
    follow: Option<&TumourFollow>,
    hz: f64,
) -> anyhow::Result<Option<RunDisease>> {
    let Some(d) = &scene.disease else {
        return Ok(None);
    };
    let mut disease = RunDisease {
        kind: d.kind.name(),
        tension: None,
        tumour: None,
        affected: None,
    };
    if let Some(engine::runtime::disease::DiseaseRun::Tension(run)) = core.disease() {
        disease.tension = Some(RunTension {
            cycles_run: run.cycles_run,
            first_arrest_cycle: run.first_arrest,
            events: run
                .events
                .iter()
                .map(|e| EventReport {
                    tick: e.tick,
                    cycle: e.cycle,
                    kind: e.kind,
                    side: e.side.name(),
                    outcome: format!("{:?}", e.outcome),
                })
                .collect(),
        });
    }
    if let (Some(engine::runtime::disease::DiseaseRun::Tumour(run)), Some(t)) =
        (core.disease(), follow)
    {
        let (amp, normal_amp) = t.amplitudes();
        let csv = args.out.join("tumour_trajectory.csv");
        t.write_csv(&csv, hz)?;
        let m = &t.meta;
        let xyz = |a: [f64; 3]| Xyz {
            x: a[0],
            y: a[1],
            z: a[2],
        };
        disease.tumour = Some(RunTumour {
            tumour: TumourRun {
                side: run.side.name(),
                centre_mm: m.centre_mm.map(r3),
                volume_ml: r3(m.volume_ml),
                vertices_affected: m.vertices_affected,
                kernel_entries_changed: m.entries_changed,
                kernel_entries_clamped: m.entries_clamped,
                affected_motion_change_percent: MeanMax {
                    mean: r3(m.affected_motion_change_percent[0]),
                    max: r3(m.affected_motion_change_percent[1]),
                },
                resistance_x: InhaleExhale {
                    inhale: run.resistance[0].x,
                    exhale: run.resistance[1].x,
                },
                trajectory_csv: csv.display().to_string(),
                trajectory_ticks: if t.last.is_empty() {
                    t.current.len()
                } else {
                    t.last.len()
                },
                non_finite_positions: t.bad,
            },
            tumour_motion_mm: xyz(amp),
            tumour_motion_normal_mm: xyz(normal_amp),
        });
    }
    if matches!(
        d.kind,
        lung_model::scene_disease::DiseaseKind::ClosedPneumothorax
            | lung_model::scene_disease::DiseaseKind::BilateralPneumothorax
    ) {
        let sides: Vec<Side> = scene.lungs.sides.clone();
        let spec = d.validate(&sides, scene.lungs.shape)?;
        if let DiseaseSpec::Closed(c) = spec {
            let per = sides
                .iter()
                .filter_map(|&side| {
                    c.index_of(side).map(|i| {
                        let dv = lung_model::disease::volume_fraction_lost(i).unwrap_or(f64::NAN);
                        AffectedLung {
                            side: side.name(),
                            pneumothorax_index: i,
                            dv: r3(dv),
                            drop_mm: r3(lung_model::disease::drop_for_index(i).drop_mm),
                        }
                    })
                })
                .collect();
            disease.affected = Some(per);
        }
    }
    Ok(Some(disease))
}

/// What `lungdyn scene run` reports (`--json` writes it; [`run_text`] prints it).
#[derive(Debug, Clone, Serialize)]
pub struct RunReport {
    /// The scene file.
    pub scene: String,
    /// The still patient's posture.
    pub posture: &'static str,
    /// Simulated seconds.
    pub seconds: f64,
    /// Ticks stepped.
    pub ticks: u64,
    /// Deformation mode.
    pub mode: String,
    /// Each simulated lung at the end.
    pub lungs: Vec<RunLung>,
    /// Ticks where a lung's volume or scale was not finite.
    pub non_finite_frames: u64,
    /// How often each stage of the tick did work.
    pub stage_counts: engine::runtime::StageCounts,
    /// The kernels used.
    pub kernels: Vec<String>,
    /// The disease state's figures (absent for normal breathing).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub disease: Option<RunDisease>,
    /// A `[pv] waveform` scene's ventilator: its control mode, why, and (with a disease) what it
    /// delivered over the run (EQUATIONS §4.7). Absent without a waveform.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ventilator: Option<RunVentilator>,
}

/// A waveform scene's ventilator as the engine ran it.
#[derive(Debug, Clone, Serialize)]
pub struct RunVentilator {
    /// The control mode and why.
    #[serde(flatten)]
    pub control: lung_model::scene::ControlChoice,
    /// The disease course's deliveries (absent without a disease).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub delivery: Option<lung_model::disease::ventilated::DeliveryLog>,
}

/// One lung of `scene run`.
#[derive(Debug, Clone, Serialize)]
pub struct RunLung {
    /// Which lung.
    pub side: &'static str,
    /// Smallest volume, ml.
    pub volume_min_ml: f64,
    /// Largest volume, ml.
    pub volume_max_ml: f64,
    /// Tidal volume of the last complete breath, ml.
    pub tidal_volume_ml: f64,
    /// Rate of the last complete breath (`null`: no complete breath).
    pub breaths_per_min: Option<f64>,
    /// Rigid offset at the end, mm.
    pub offset_mm: [f64; 3],
    /// Collapse at the end.
    pub collapse: f64,
    /// Whether the lung is held (not breathing).
    pub held: bool,
    /// The mode's coefficients at the end.
    pub coefficients: Vec<f64>,
    /// Breathing cycles.
    pub cycles: u32,
}

/// The disease state's figures of `scene run`.
#[derive(Debug, Clone, Serialize)]
pub struct RunDisease {
    /// The `[disease] kind`.
    pub kind: &'static str,
    /// A tension pneumothorax's run.
    #[serde(flatten)]
    pub tension: Option<RunTension>,
    /// A tumour's run.
    #[serde(flatten)]
    pub tumour: Option<RunTumour>,
    /// A closed pneumothorax's affected lungs.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub affected: Option<Vec<AffectedLung>>,
}

/// A tension pneumothorax as the engine ran it.
#[derive(Debug, Clone, Serialize)]
pub struct RunTension {
    /// Cycles since the onset.
    pub cycles_run: u64,
    /// First cycle in arrest.
    pub first_arrest_cycle: Option<u64>,
    /// The interventions as applied.
    pub events: Vec<EventReport>,
}

/// A tumour as the engine ran it.
#[derive(Debug, Clone, Serialize)]
pub struct RunTumour {
    /// The baked tumour and its trajectory file.
    pub tumour: TumourRun,
    /// The centre's motion over the last breath, mm.
    pub tumour_motion_mm: Xyz,
    /// The same point's motion without the tumour, mm.
    pub tumour_motion_normal_mm: Xyz,
}

/// The baked tumour of `scene run`.
#[derive(Debug, Clone, Serialize)]
pub struct TumourRun {
    /// The lung.
    pub side: &'static str,
    /// Centre at rest, mm.
    pub centre_mm: [f64; 3],
    /// Volume, ml.
    pub volume_ml: f64,
    /// Vertices with expandability below 1.
    pub vertices_affected: u64,
    /// Kernel entries changed.
    pub kernel_entries_changed: u64,
    /// Kernel entries clamped.
    pub kernel_entries_clamped: u64,
    /// Change of the surface motion where the tumour reaches, %.
    pub affected_motion_change_percent: MeanMax,
    /// Raised resistance factors.
    pub resistance_x: InhaleExhale,
    /// The trajectory file.
    pub trajectory_csv: String,
    /// Ticks in it.
    pub trajectory_ticks: usize,
    /// Positions that were not finite.
    pub non_finite_positions: u64,
}

/// A closed pneumothorax's affected lung in `scene run`.
#[derive(Debug, Clone, Serialize)]
pub struct AffectedLung {
    /// Which lung.
    pub side: &'static str,
    /// Pneumothorax index I.
    pub pneumothorax_index: f64,
    /// Volume fraction lost.
    #[serde(rename = "dV")]
    pub dv: f64,
    /// Base drop, mm.
    pub drop_mm: f64,
}

/// Three components.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Xyz {
    /// X.
    pub x: f64,
    /// Y.
    pub y: f64,
    /// Z.
    pub z: f64,
}

/// A mean and a largest value.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct MeanMax {
    /// Mean.
    pub mean: f64,
    /// Largest.
    pub max: f64,
}

/// The `scene run` report as text.
pub fn run_text(r: &RunReport) -> String {
    let mut s = format!(
        "{}: {} s simulated ({} ticks, mode {}, patient {} and still){}\n",
        r.scene,
        j(&r.seconds),
        r.ticks,
        r.mode,
        r.posture,
        if r.non_finite_frames == 0 {
            String::new()
        } else {
            format!(", {} NON-FINITE frames", r.non_finite_frames)
        }
    );
    for l in &r.lungs {
        s += &format!(
            "  {} lung: {}–{} ml, last breath {} ml at {} /min, offset {} mm, collapse {}{}\n",
            l.side,
            j(&l.volume_min_ml),
            j(&l.volume_max_ml),
            j(&l.tidal_volume_ml),
            j(&l.breaths_per_min),
            j(&l.offset_mm),
            j(&l.collapse),
            if l.held { ", HELD (not breathing)" } else { "" }
        );
    }
    if let Some(d) = &r.disease {
        s += &format!("  disease {}", d.kind);
        if let Some(t) = &d.tension {
            s += &format!(
                ": {} cycles, {}",
                t.cycles_run,
                match t.first_arrest_cycle {
                    Some(a) => format!("arrest at cycle {a}"),
                    None => "no arrest".to_string(),
                }
            );
        }
        s += "\n";
        if let Some(t) = &d.tumour {
            let (m, n) = (&t.tumour_motion_mm, &t.tumour_motion_normal_mm);
            s += &format!(
                "  tumour centre {} mm moves {} / {} / {} mm (x / y / z) over the last breath (without \
                 the tumour: {} / {} / {} mm); trajectory in {}\n",
                j(&t.tumour.centre_mm),
                j(&m.x),
                j(&m.y),
                j(&m.z),
                j(&n.x),
                j(&n.y),
                j(&n.z),
                t.tumour.trajectory_csv
            );
        }
        if let Some(t) = &d.tension {
            s += &event_lines(&t.events);
        }
    }
    if let Some(v) = &r.ventilator {
        s += &format!(
            "  ventilator: {} control (set by the {}; the recording: {})\n",
            v.control.mode.name(),
            v.control.set_by,
            v.control.recording
        );
        if let Some(d) = &v.delivery {
            s += &format!(
                "  delivered over {} cycles: at least {} of the recorded volume{}\n",
                d.cycles,
                d.lowest_fraction
                    .map_or_else(|| "none".to_string(), |f| j(&r3(f))),
                if d.pressure_capped_cycles > 0 {
                    format!(
                        "; the pressure limit capped {} cycles",
                        d.pressure_capped_cycles
                    )
                } else {
                    String::new()
                }
            );
        }
    }
    s += &format!("  stage counts: {}\n", j(&r.stage_counts));
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn keys(v: &serde_json::Value) -> Vec<&str> {
        let mut k: Vec<&str> = v
            .as_object()
            .expect("an object")
            .keys()
            .map(String::as_str)
            .collect();
        k.sort_unstable();
        k
    }

    /// The report's JSON keys are what scripts read (`scene check --json`); the text is built from
    /// the same typed fields and shows the figures as the JSON writes them.
    #[test]
    fn the_check_report_keeps_its_json_keys_and_its_text_shows_the_same_figures() {
        let scenes = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes");
        let check = |file: &str| {
            run(&CheckArgs {
                file: scenes.join(file),
                cycles: 40,
                json: true,
            })
            .unwrap()
        };
        let r = check("tension_pneumothorax.toml");
        let v = serde_json::to_value(&r).unwrap();
        assert_eq!(
            keys(&v),
            ["bands", "disease", "lungs", "mode", "pv", "render", "scene", "valid"]
        );
        assert_eq!(
            keys(&v["pv"]),
            [
                "breaths_per_min",
                "constants",
                "frc_ml",
                "preset",
                "tidal_volume_ml",
                "waveform",
                "waveform_breaths_used"
            ]
        );
        assert_eq!(keys(&v["render"]), ["calibration", "hmd"]);
        let d = &v["disease"];
        assert_eq!(
            keys(d),
            [
                "atmospheric_air_ml",
                "course",
                "cycles_to_arrest",
                "engine_applies_it",
                "events",
                "final",
                "kind",
                "model",
                "normal_cycles_before_onset",
                "onset_s",
                "shift_mm_per_ml",
                "side",
                "svc_closing_air_ml",
                "v1_max_ml",
                "v2_max_ml"
            ]
        );
        assert_eq!(d["kind"], "tension-pneumothorax");
        assert_eq!(d["events"][0]["kind"], "needle-decompression");
        assert_eq!(
            keys(&d["final"]),
            [
                "affected_tidal_ml",
                "arrest",
                "breaths_per_min",
                "cycle",
                "dV",
                "drop_mm",
                "minute_ventilation_l_per_min",
                "other_base_volume_ml",
                "other_tidal_ml",
                "pleural_air_ml",
                "shift_mm",
                "start_tick",
                "svc_closed"
            ]
        );
        let t = text(&r);
        assert!(t.contains(&format!("FRC {} ml", v["pv"]["frc_ml"])), "{t}");
        assert!(
            t.contains(&format!(
                "event at tick {} (cycle {}): needle-decompression left — applied",
                d["events"][0]["tick"], d["events"][0]["cycle"]
            )),
            "{t}"
        );
        assert!(t.contains(&format!("V1max {} ml", d["v1_max_ml"])), "{t}");

        let r = check("bilateral_pneumothorax.toml");
        let v = serde_json::to_value(&r).unwrap();
        let d = &v["disease"];
        assert_eq!(
            keys(d),
            [
                "breaths_per_min",
                "engine_applies_it",
                "exhale_s",
                "inhale_s",
                "kind",
                "lungs",
                "minute_ventilation_l_per_min",
                "model",
                "phase_clamped"
            ]
        );
        assert_eq!(
            keys(&d["lungs"][0]),
            [
                "base_lift_mm",
                "base_volume_ml",
                "dV",
                "drop_clamped",
                "drop_mm",
                "held_ml",
                "offset_mm",
                "pneumothorax_index",
                "side",
                "tidal_volume_ml"
            ]
        );
        let l = &d["lungs"][1];
        assert!(
            text(&r).contains(&format!(
                "{} lung: I = {}, dV = {}, drop {} mm",
                l["side"].as_str().unwrap(),
                l["pneumothorax_index"],
                l["dV"],
                l["drop_mm"]
            )),
            "{}",
            text(&r)
        );

        let r = check("default.toml");
        let v = serde_json::to_value(&r).unwrap();
        assert!(v["disease"].is_null() && v["render"]["calibration"].is_null());
        assert!(text(&r).ends_with("no disease state: normal breathing\n"));
    }
}
