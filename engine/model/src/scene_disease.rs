//! # scene_disease: the `[disease]` table of a scene, checked and resolved
//!
//! The table's types are `lungdyn-scene`'s (`lungdyn_scene::disease`, re-exported here); its checks
//! need the disease models and the lungs' shapes, so they are here, as [`DiseaseSceneExt`]. What a
//! scene says about a disease state (docs/EQUATIONS.md §4): its kind, the parameters of that
//! kind and — for a tension pneumothorax — the trainee's interventions as timed events:
//!
//! ```toml
//! [disease]
//! kind = "tension-pneumothorax"   # "closed-pneumothorax" | "bilateral-pneumothorax" | "tumour"
//! model = "clinical"              # (default) | "seed": the seed's literal reading (EQUATIONS §4.6)
//! side = "left"
//! v_p_ml = 5.0                    # eq. 8.10 V_p, ml in the first cycle
//! tau = 0.001                     # eq. 8.10 τ, per cycle
//!
//! [[disease.events]]
//! at_s = 30
//! kind = "needle-decompression"   # | "occlusive-dressing" | "chest-tube"
//! side = "left"
//! ```
//!
//! Unknown keys are refused by serde (with the parser's line and column). A key that exists but does
//! not apply to the kind, a missing key and a value out of range are refused by [`DiseaseSceneExt::resolve`]
//! with an error that names the key. Every key but the kind's required ones has a documented default
//! (the `disease` module's constants). Checks that need the lungs (`v1_max_ml` against the affected
//! lung's volume, the tumour centre inside the lung) are made when the state is built from them.
//!
//! Documented conversions: `at_s` becomes the engine tick `round(at_s·tick_hz)` ([`TimedEvent::tick`]);
//! events are applied in time order (a stable sort: events at the same time keep the file's order).

pub use lungdyn_scene::disease::{
    DiseaseKind, DiseaseScene, EventScene, TumourScene, MAX_EVENTS, MAX_TIME_S,
};

use thiserror::Error;

use crate::disease::closed::ClosedPneumothorax;
use crate::disease::tension::{Intervention, TensionParams};
use crate::disease::tumour::Tumour;
use crate::disease::{resistance::PHI_SEED, CourseModel, DiseaseError, ALPHA_SEED_ML};
use crate::mesh::generate::Shape;
use crate::mesh::Side;

/// The tumour's centre in normalised lung coordinates from `centre` and/or `lobe` (see
/// [`TumourScene::lobe`]); a lobe alone gives its interior point in the lung of `shape` (the scene's
/// `[lungs] shape`).
fn tumour_centre(side: Side, shape: Shape, t: &TumourScene) -> Result<[f64; 3], DiseaseSceneError> {
    use crate::mesh::lobes::{interior_point, Fissures, Lobe};
    let Some(name) = &t.lobe else {
        return t.centre.ok_or(DiseaseSceneError::Missing {
            key: "tumour.centre (or tumour.lobe)",
            kind: "tumour",
        });
    };
    let lobe: Lobe = name.parse().map_err(DiseaseSceneError::Lobe)?;
    if lobe.side() != Some(side) {
        return Err(DiseaseSceneError::Lobe(format!(
            "the {lobe} lobe is not in the {} lung (side = \"{}\")",
            side.name(),
            side.name()
        )));
    }
    match t.centre {
        Some(c) => {
            let found = Fissures::adult(side).lobe_at(side, c);
            if found != lobe {
                return Err(DiseaseSceneError::Lobe(format!(
                    "centre {c:?} lies in the {found} lobe, not the {lobe} lobe (fissure planes in \
                     normalised coordinates: mesh::lobes); move centre or drop it to use the lobe's \
                     interior point"
                )));
            }
            Ok(c)
        }
        None => interior_point(shape, lobe).ok_or_else(|| {
            DiseaseSceneError::Lobe(format!(
                "no interior point found for the {lobe} lobe of the {shape} lung"
            ))
        }),
    }
}

/// An intervention at a validated time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TimedEvent {
    /// Time from the scene's start, s.
    pub at_s: f64,
    /// What is done.
    pub kind: Intervention,
    /// On which side.
    pub side: Side,
}

impl TimedEvent {
    /// The engine tick the event arrives at: `round(at_s·tick_hz)`.
    pub fn tick(&self, tick_hz: f64) -> u64 {
        (self.at_s * tick_hz).round() as u64
    }
}

/// A disease state ready to build against the scene's lungs.
#[derive(Debug, Clone, PartialEq)]
pub enum DiseaseSpec {
    /// Closed pneumothorax of one or both lungs.
    Closed(ClosedPneumothorax),
    /// Tension pneumothorax.
    Tension {
        /// Its parameters.
        params: TensionParams,
        /// Onset, s from the scene's start.
        onset_s: f64,
        /// Interventions in time order.
        events: Vec<TimedEvent>,
    },
    /// Tumour.
    Tumour(Tumour),
}

impl DiseaseSpec {
    /// The lungs this state affects.
    pub fn affected(&self) -> Vec<Side> {
        match self {
            DiseaseSpec::Closed(c) => [Side::Right, Side::Left]
                .into_iter()
                .filter(|&s| c.index_of(s).is_some())
                .collect(),
            DiseaseSpec::Tension { params, .. } => vec![params.side],
            DiseaseSpec::Tumour(t) => vec![t.side],
        }
    }
}

/// What is wrong with a `[disease]` table; every variant names the key.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum DiseaseSceneError {
    /// A key the kind needs is absent.
    #[error("[disease] {key} is required for kind = \"{kind}\"")]
    Missing {
        /// The key.
        key: &'static str,
        /// The kind.
        kind: &'static str,
    },
    /// A key is present that the kind does not use.
    #[error("[disease] {key} does not apply to kind = \"{kind}\" (it uses: {uses})")]
    NotApplicable {
        /// The key.
        key: &'static str,
        /// The kind.
        kind: &'static str,
        /// The keys the kind uses.
        uses: &'static str,
    },
    /// A value is out of range or inconsistent (the inner error names the key).
    #[error("[disease] {0}")]
    Value(#[source] DiseaseError),
    /// `[disease.tumour]` lobe is unusable: unknown, in the other lung, or not where the centre is.
    #[error("[disease.tumour] lobe: {0}")]
    Lobe(String),
    /// An event is unusable.
    #[error("[[disease.events]] number {number} (at_s = {at_s}): {reason}")]
    Event {
        /// 1-based position in the file.
        number: usize,
        /// Its time.
        at_s: f64,
        /// What is wrong.
        reason: String,
    },
    /// Too many events.
    #[error("[[disease.events]] lists {count} events; at most {MAX_EVENTS}")]
    TooManyEvents {
        /// Number given.
        count: usize,
    },
    /// The state affects a lung the scene does not simulate.
    #[error("[disease] affects the {side} lung, which [lungs] sides does not list")]
    LungNotSimulated {
        /// "left" or "right".
        side: &'static str,
    },
}

impl From<DiseaseError> for DiseaseSceneError {
    fn from(e: DiseaseError) -> Self {
        DiseaseSceneError::Value(e)
    }
}

/// What the physics makes of a `[disease]` table: its keys checked for its kind, its values against
/// the models' ranges and the scene's lungs, and the [`DiseaseSpec`] that builds the state.
pub trait DiseaseSceneExt {
    /// Validate and convert into a [`DiseaseSpec`] (everything that does not need the lungs but
    /// their `shape`, `[lungs] shape`: a tumour placed by lobe alone sits inside that shape's lobe).
    fn resolve(&self, shape: Shape) -> Result<DiseaseSpec, DiseaseSceneError>;

    /// [`Self::validate`] for a scene whose breath is a ventilator recording (`[pv] waveform`;
    /// EQUATIONS §4.7): the ventilator delivers the recorded volume and the lungs share it, so what
    /// shapes a spontaneous breath does not apply and is refused when given — `alpha_ml` (eq. 8.7's
    /// extra effort: a passive patient makes none), `phi` and `tumour.resistance_phi` (eq. 8.8–8.9
    /// reshape the PV model's curve; under volume control the resistance changes the airway pressure,
    /// not the delivered volume) — and so is a closed pneumothorax that collapses every simulated
    /// lung completely (no lung is left to take the recorded volume). α is 0 in the spec returned.
    fn validate_ventilated(
        &self,
        sides: &[Side],
        shape: Shape,
    ) -> Result<DiseaseSpec, DiseaseSceneError>;

    /// [`Self::resolve`] and check the affected lungs are among the scene's `sides`.
    fn validate(&self, sides: &[Side], shape: Shape) -> Result<DiseaseSpec, DiseaseSceneError>;
}

impl DiseaseSceneExt for DiseaseScene {
    fn resolve(&self, shape: Shape) -> Result<DiseaseSpec, DiseaseSceneError> {
        check_keys(self)?;
        let kind = self.kind.name();
        let side = || {
            self.side
                .ok_or(DiseaseSceneError::Missing { key: "side", kind })
        };
        let phi = self.phi.unwrap_or(PHI_SEED);
        let alpha = self.alpha_ml.unwrap_or(ALPHA_SEED_ML);
        match self.kind {
            DiseaseKind::ClosedPneumothorax => {
                let index = self
                    .index
                    .ok_or(DiseaseSceneError::Missing { key: "index", kind })?;
                // Validate under the scene's key name `index`.
                crate::disease::volume_fraction_lost(index)?;
                let c = ClosedPneumothorax::unilateral(side()?, index, alpha, phi)
                    .with_model(self.model.unwrap_or_default());
                c.validate()?;
                Ok(DiseaseSpec::Closed(c))
            }
            DiseaseKind::BilateralPneumothorax => {
                let l = self.index_left.ok_or(DiseaseSceneError::Missing {
                    key: "index_left",
                    kind,
                })?;
                let r = self.index_right.ok_or(DiseaseSceneError::Missing {
                    key: "index_right",
                    kind,
                })?;
                let c = ClosedPneumothorax::bilateral(l, r, phi)
                    .with_model(self.model.unwrap_or_default());
                c.validate()?;
                Ok(DiseaseSpec::Closed(c))
            }
            DiseaseKind::TensionPneumothorax => tension(self, side()?, alpha, phi),
            DiseaseKind::Tumour => tumour_spec(self, shape),
        }
    }

    fn validate_ventilated(
        &self,
        sides: &[Side],
        shape: Shape,
    ) -> Result<DiseaseSpec, DiseaseSceneError> {
        const EFFORT: &str =
            "a ventilated patient's breath is the recording's ([pv] waveform): the \
             ventilator delivers it, a passive patient adds no extra effort (eq. 8.7; EQUATIONS \
             §4.7); drop the key";
        const RESISTANCE: &str =
            "eq. 8.8-8.9 reshape the PV model's breath; a ventilator delivers \
             the recorded volume whatever the resistance (volume control: resistance raises the \
             airway pressure, P = V/C + R·flow + P0, not the volume; EQUATIONS §4.7); drop the key";
        for (name, present, reason) in [
            ("alpha_ml", self.alpha_ml.is_some(), EFFORT),
            ("phi", self.phi.is_some(), RESISTANCE),
            (
                "tumour.resistance_phi",
                self.tumour
                    .as_ref()
                    .is_some_and(|t| t.resistance_phi.is_some()),
                RESISTANCE,
            ),
        ] {
            if present {
                return Err(DiseaseError::NotApplicable { name, reason }.into());
            }
        }
        let mut spec = self.validate(sides, shape)?;
        match &mut spec {
            DiseaseSpec::Closed(c) => {
                if sides.iter().all(|&s| c.index_of(s) == Some(1.0)) {
                    return Err(DiseaseError::NotApplicable {
                        name: "index",
                        reason: "every simulated lung collapses completely (index 1): no lung is \
                                 left to take the ventilator's recorded volume ([pv] waveform; \
                                 EQUATIONS §4.7)",
                    }
                    .into());
                }
                c.alpha_ml = 0.0;
            }
            DiseaseSpec::Tension { params, .. } => params.alpha_ml = 0.0,
            DiseaseSpec::Tumour(_) => {}
        }
        Ok(spec)
    }

    fn validate(&self, sides: &[Side], shape: Shape) -> Result<DiseaseSpec, DiseaseSceneError> {
        let spec = self.resolve(shape)?;
        for s in spec.affected() {
            if !sides.contains(&s) {
                return Err(DiseaseSceneError::LungNotSimulated { side: s.name() });
            }
        }
        Ok(spec)
    }
}

/// The keys present, by name (for the applicability check).
fn present(this: &DiseaseScene) -> [(&'static str, bool); 23] {
    [
        ("side", this.side.is_some()),
        ("index", this.index.is_some()),
        ("index_left", this.index_left.is_some()),
        ("index_right", this.index_right.is_some()),
        ("alpha_ml", this.alpha_ml.is_some()),
        ("phi", this.phi.is_some()),
        ("onset_s", this.onset_s.is_some()),
        ("source", this.source.is_some()),
        ("v_p_ml", this.v_p_ml.is_some()),
        ("tau", this.tau.is_some()),
        ("v1_max_ml", this.v1_max_ml.is_some()),
        ("v2_max_ml", this.v2_max_ml.is_some()),
        ("beta_mm", this.beta_mm.is_some()),
        ("needle_vent_cycles", this.needle_vent_cycles.is_some()),
        ("needle_residual", this.needle_residual.is_some()),
        (
            "chest_tube_ml_per_cycle",
            this.chest_tube_ml_per_cycle.is_some(),
        ),
        (
            "hyperexpansion_cycles",
            this.hyperexpansion_cycles.is_some(),
        ),
        ("tumour", this.tumour.is_some()),
        ("events", !this.events.is_empty()),
        ("model", this.model.is_some()),
        (
            "mediastinal_compliance_ml_per_cmh2o",
            this.mediastinal_compliance_ml_per_cmh2o.is_some(),
        ),
        ("needle_tau_cycles", this.needle_tau_cycles.is_some()),
        (
            "contralateral_compression",
            this.contralateral_compression.is_some(),
        ),
    ]
}

/// Every key given applies to this kind (and, for a tension pneumothorax, to its model).
fn check_keys(this: &DiseaseScene) -> Result<(), DiseaseSceneError> {
    let kind = this.kind.name();
    let uses: &'static str = match this.kind {
        DiseaseKind::ClosedPneumothorax => "model, side, index, alpha_ml, phi",
        DiseaseKind::BilateralPneumothorax => "model, index_left, index_right, phi",
        DiseaseKind::TensionPneumothorax => match this.model.unwrap_or_default() {
            CourseModel::Seed => {
                "model, side, alpha_ml, phi, onset_s, source, v_p_ml, tau, v1_max_ml, v2_max_ml, \
                 beta_mm, needle_vent_cycles, needle_residual, chest_tube_ml_per_cycle, \
                 hyperexpansion_cycles, events"
            }
            CourseModel::Clinical => {
                "model, side, alpha_ml, phi, onset_s, source, v_p_ml, tau, v1_max_ml, v2_max_ml, \
                 beta_mm, mediastinal_compliance_ml_per_cmh2o, needle_tau_cycles, \
                 contralateral_compression, chest_tube_ml_per_cycle, hyperexpansion_cycles, \
                 events"
            }
        },
        DiseaseKind::Tumour => "side, tumour",
    };
    if this.kind == DiseaseKind::TensionPneumothorax {
        let model = this.model.unwrap_or_default();
        let (keys, reason): (&[(&'static str, bool)], &'static str) = match model {
            CourseModel::Clinical => (
                &[
                    ("needle_vent_cycles", this.needle_vent_cycles.is_some()),
                    ("needle_residual", this.needle_residual.is_some()),
                ],
                "applies to model = \"seed\" only (the clinical needle vents to atmospheric \
                 pleural pressure with time constant needle_tau_cycles; EQUATIONS §4.6)",
            ),
            CourseModel::Seed => (
                &[
                    (
                        "mediastinal_compliance_ml_per_cmh2o",
                        this.mediastinal_compliance_ml_per_cmh2o.is_some(),
                    ),
                    ("needle_tau_cycles", this.needle_tau_cycles.is_some()),
                    (
                        "contralateral_compression",
                        this.contralateral_compression.is_some(),
                    ),
                ],
                "applies to model = \"clinical\" only (EQUATIONS §4.6)",
            ),
        };
        if let Some(&(name, _)) = keys.iter().find(|k| k.1) {
            return Err(DiseaseError::NotApplicable { name, reason }.into());
        }
    }
    for (key, present) in present(this) {
        if present && !uses.split(", ").any(|k| k == key) {
            return Err(DiseaseSceneError::NotApplicable { key, kind, uses });
        }
    }
    Ok(())
}

/// A tension pneumothorax's parameters (each key's default where not given), its onset and
/// its timed events.
fn tension(
    this: &DiseaseScene,
    side: Side,
    alpha: f64,
    phi: f64,
) -> Result<DiseaseSpec, DiseaseSceneError> {
    let d = TensionParams::new(side);
    let params = TensionParams {
        source: this.source.unwrap_or(d.source),
        inflow_ml: this.v_p_ml.unwrap_or(d.inflow_ml),
        tau: this.tau.unwrap_or(d.tau),
        v1_max_ml: this.v1_max_ml,
        v2_max_ml: this.v2_max_ml,
        beta_mm: this.beta_mm.unwrap_or(d.beta_mm),
        alpha_ml: alpha,
        phi,
        needle_vent_cycles: this.needle_vent_cycles.unwrap_or(d.needle_vent_cycles),
        needle_residual: this.needle_residual.unwrap_or(d.needle_residual),
        chest_tube_ml_per_cycle: this
            .chest_tube_ml_per_cycle
            .unwrap_or(d.chest_tube_ml_per_cycle),
        hyperexpansion_cycles: this
            .hyperexpansion_cycles
            .unwrap_or(d.hyperexpansion_cycles),
        model: this.model.unwrap_or_default(),
        mediastinal_compliance_ml_per_cmh2o: this
            .mediastinal_compliance_ml_per_cmh2o
            .unwrap_or(d.mediastinal_compliance_ml_per_cmh2o),
        needle_tau_cycles: this.needle_tau_cycles.unwrap_or(d.needle_tau_cycles),
        contralateral_compression: match this.model.unwrap_or_default() {
            CourseModel::Seed => 0.0,
            CourseModel::Clinical => this
                .contralateral_compression
                .unwrap_or(d.contralateral_compression),
        },
        ..d
    };
    params.validate()?;
    for (key, v) in [
        ("v1_max_ml", params.v1_max_ml),
        ("v2_max_ml", params.v2_max_ml),
    ] {
        if let Some(v) = v {
            crate::disease::check_range(key, v, f64::MIN_POSITIVE, 6000.0, "within (0, 6000] ml")?;
        }
    }
    let onset_s = crate::disease::check_range(
        "onset_s",
        this.onset_s.unwrap_or(0.0),
        0.0,
        MAX_TIME_S,
        "within 0..=1e7 s",
    )?;
    let events = tension_events(this, onset_s)?;
    Ok(DiseaseSpec::Tension {
        params,
        onset_s,
        events,
    })
}

/// The timed events, checked (within the run's time, not before the onset) and sorted by time.
fn tension_events(this: &DiseaseScene, onset_s: f64) -> Result<Vec<TimedEvent>, DiseaseSceneError> {
    if this.events.len() > MAX_EVENTS {
        return Err(DiseaseSceneError::TooManyEvents {
            count: this.events.len(),
        });
    }
    let mut events = Vec::with_capacity(this.events.len());
    for (k, e) in this.events.iter().enumerate() {
        let bad = |reason: String| DiseaseSceneError::Event {
            number: k + 1,
            at_s: e.at_s,
            reason,
        };
        if !(e.at_s.is_finite() && (0.0..=MAX_TIME_S).contains(&e.at_s)) {
            return Err(bad("at_s must be within 0..=1e7 s".into()));
        }
        if e.at_s < onset_s {
            return Err(bad(format!(
                "at_s is before onset_s = {onset_s} s: there is nothing to treat yet"
            )));
        }
        events.push(TimedEvent {
            at_s: e.at_s,
            kind: e.kind,
            side: e.side,
        });
    }
    // Stable: events at the same time keep the file's order.
    events.sort_by(|a, b| a.at_s.total_cmp(&b.at_s));
    Ok(events)
}

/// A tumour placed by centre or by lobe in `shape`, each key's default where not given.
fn tumour_spec(this: &DiseaseScene, shape: Shape) -> Result<DiseaseSpec, DiseaseSceneError> {
    let kind = this.kind.name();
    let t = this.tumour.as_ref().ok_or(DiseaseSceneError::Missing {
        key: "tumour",
        kind,
    })?;
    let side = this
        .side
        .ok_or(DiseaseSceneError::Missing { key: "side", kind })?;
    let centre = tumour_centre(side, shape, t)?;
    let d = Tumour::new(side, centre, t.radii_mm);
    let tumour = Tumour {
        expandability: t.expandability.unwrap_or(d.expandability),
        falloff: t.falloff.unwrap_or(d.falloff),
        coupling: t.coupling.unwrap_or(d.coupling),
        phi: t.phi_variant.unwrap_or(d.phi),
        resistance_phi: t.resistance_phi.unwrap_or(d.resistance_phi),
        ..d
    };
    tumour.validate()?;
    Ok(DiseaseSpec::Tumour(tumour))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::disease::tension::LeakSource;
    use crate::disease::tumour::PhiVariant;
    use crate::scene::{Scene, SceneExt};

    /// A scene's error names `[disease]` once (it read "[disease]: [disease] index = 2 …").
    #[test]
    fn a_bad_value_names_its_table_once() {
        let scene: crate::scene::Scene = toml::from_str(
            "[disease]\nkind = \"closed-pneumothorax\"\nside = \"left\"\nindex = 2.0\n",
        )
        .unwrap();
        let e = scene.validate().unwrap_err().to_string();
        assert_eq!(e.matches("[disease]").count(), 1, "{e}");
        assert!(e.contains("index = 2"), "{e}");
    }

    fn disease(toml_text: &str) -> DiseaseScene {
        let scene: Scene = toml::from_str(toml_text).unwrap();
        scene.disease.unwrap()
    }

    #[test]
    fn the_seeds_closed_pneumothorax_scene() {
        let d = disease("[disease]\nkind = \"closed-pneumothorax\"\nside = \"left\"\nindex = 0.1\nalpha_ml = 100\n");
        let spec = d
            .validate(&[Side::Right, Side::Left], Shape::Anatomical)
            .unwrap();
        assert_eq!(
            spec,
            DiseaseSpec::Closed(ClosedPneumothorax::unilateral(Side::Left, 0.1, 100.0, 0.1))
        );
        assert_eq!(
            ClosedPneumothorax::unilateral(Side::Left, 0.1, 100.0, 0.1).model,
            CourseModel::Clinical
        );
        assert!(matches!(
            d.validate(&[Side::Right], Shape::Anatomical),
            Err(DiseaseSceneError::LungNotSimulated { side: "left" })
        ));
    }

    #[test]
    fn a_tension_scene_with_events_in_time_order() {
        let d = disease(
            "[disease]\nkind = \"tension-pneumothorax\"\nside = \"left\"\nsource = \"wound\"\ntau = 0\nonset_s = 5\n\
             [[disease.events]]\nat_s = 60\nkind = \"chest-tube\"\nside = \"left\"\n\
             [[disease.events]]\nat_s = 30.5\nkind = \"needle-decompression\"\nside = \"left\"\n\
             [[disease.events]]\nat_s = 60\nkind = \"occlusive-dressing\"\nside = \"left\"\n",
        );
        let DiseaseSpec::Tension {
            params,
            onset_s,
            events,
        } = d.resolve(Shape::Anatomical).unwrap()
        else {
            panic!("not a tension spec");
        };
        assert_eq!(
            (params.tau, params.source, onset_s),
            (0.0, LeakSource::Wound, 5.0)
        );
        assert_eq!(params.inflow_ml, crate::disease::tension::INFLOW_ML);
        let kinds: Vec<_> = events.iter().map(|e| e.kind).collect();
        assert_eq!(
            kinds,
            [
                Intervention::NeedleDecompression,
                Intervention::ChestTube,
                Intervention::OcclusiveDressing
            ]
        );
        // 30.5 s at 60 Hz = tick 1830.
        assert_eq!(events[0].tick(60.0), 1830);
    }

    #[test]
    fn bilateral_and_tumour_scenes() {
        let d = disease(
            "[disease]\nkind = \"bilateral-pneumothorax\"\nindex_left = 0.1\nindex_right = 0.05\n",
        );
        assert!(
            matches!(d.resolve(Shape::Anatomical).unwrap(), DiseaseSpec::Closed(c) if c.alpha_ml == 0.0)
        );
        let d = disease(
            "[disease]\nkind = \"tumour\"\nside = \"right\"\n[disease.tumour]\ncentre = [0.5, 0.4, 0.8]\n\
             radii_mm = [15, 15, 20]\nphi_variant = \"distance-squared\"\n",
        );
        let DiseaseSpec::Tumour(t) = d.resolve(Shape::Anatomical).unwrap() else {
            panic!("not a tumour");
        };
        assert_eq!((t.phi, t.expandability), (PhiVariant::DistanceSquared, 0.1));
    }

    #[test]
    fn a_tumour_can_be_placed_by_lobe() {
        use crate::mesh::lobes::{Fissures, Lobe};
        let scene = |side: &str, extra: &str| {
            disease(&format!(
                "[disease]\nkind = \"tumour\"\nside = \"{side}\"\n[disease.tumour]\n\
                 radii_mm = [10, 10, 10]\n{extra}"
            ))
            .resolve(Shape::Anatomical)
        };
        // The lobe alone: a centre inside that lobe.
        for (side, name, lobe) in [
            ("right", "right lower", Lobe::RightLower),
            ("right", "RML", Lobe::RightMiddle),
            ("left", "left-upper", Lobe::LeftUpper),
        ] {
            let Ok(DiseaseSpec::Tumour(t)) = scene(side, &format!("lobe = \"{name}\"\n")) else {
                panic!("{name}");
            };
            assert_eq!(Fissures::adult(t.side).lobe_at(t.side, t.centre), lobe);
        }
        // A centre and its lobe agree: kept as given.
        let Ok(DiseaseSpec::Tumour(t)) = scene(
            "right",
            "lobe = \"right lower\"\ncentre = [0.6, 0.3, 0.8]\n",
        ) else {
            panic!("agreeing centre refused");
        };
        assert_eq!(t.centre, [0.6, 0.3, 0.8]);
        // Disagreements and mistakes are named.
        for (side, extra, needle) in [
            (
                "right",
                "lobe = \"right upper\"\ncentre = [0.6, 0.3, 0.8]\n",
                "lies in the right lower lobe, not the right upper",
            ),
            ("right", "lobe = \"left lower\"\n", "not in the right lung"),
            ("left", "lobe = \"left middle\"\n", "unknown lobe"),
            ("left", "", "tumour.centre (or tumour.lobe)"),
        ] {
            let e = scene(side, extra).unwrap_err().to_string();
            assert!(e.contains(needle), "{e}");
        }
    }

    /// A tumour placed by lobe alone sits in the middle of that lobe of the scene's own lung shape:
    /// its centre is within 10 mm of the centroid of the lobe's interior, estimated here on a finer
    /// grid than `interior_point` uses (28³ cells against 24³). (Before the shape was passed, a teardrop scene got
    /// the anatomical lung's point, 25 mm from the teardrop's lower-lobe centroid.)
    #[test]
    fn a_lobe_places_the_tumour_in_the_scenes_own_lung_shape() {
        use crate::disease::tumour::winding_number;
        use crate::mesh::lobes::{normalise, Fissures, Lobe};
        use rayon::prelude::*;
        for shape in Shape::ALL {
            for (side, lobe) in [("right", Lobe::RightLower), ("left", Lobe::LeftLower)] {
                let scene = Scene::parse(
                    &format!(
                        "[lungs]\nshape = \"{shape}\"\n[disease]\nkind = \"tumour\"\nside = \"{side}\"\n\
                         [disease.tumour]\nlobe = \"{}\"\nradii_mm = [10, 10, 10]\n",
                        lobe.name()
                    ),
                    "test",
                )
                .unwrap();
                let t = scene.tumour().unwrap();
                let mesh = crate::mesh::generate::lung_of(shape, t.side, 2_000).unwrap();
                let bb = mesh.aabb();
                let (lo, hi) = (bb.min.map(|v| v as f64), bb.max.map(|v| v as f64));
                const N: usize = 28;
                let (sum, count) = (0..N * N * N)
                    .into_par_iter()
                    .filter_map(|g| {
                        let f =
                            [g / (N * N), g / N % N, g % N].map(|g| (g as f64 + 0.5) / N as f64);
                        let p = [0, 1, 2].map(|a| lo[a] + f[a] * (hi[a] - lo[a]));
                        let n = normalise(t.side, &bb, p);
                        (Fissures::adult(t.side).lobe_at(t.side, n) == lobe
                            && winding_number(&mesh, p) > 0.5)
                            .then(|| (glam::DVec3::from(p), 1.0))
                    })
                    .reduce(|| (glam::DVec3::ZERO, 0.0), |a, b| (a.0 + b.0, a.1 + b.1));
                let centroid = sum / count;
                let centre = glam::DVec3::from(t.centre_mm(&mesh));
                let d = centre.distance(centroid);
                assert!(
                    d < 10.0,
                    "{shape} {lobe}: centre {centre:.1} is {d:.1} mm from the lobe's centroid \
                     {centroid:.1}"
                );
            }
        }
    }

    #[test]
    fn every_mistake_names_its_key() {
        let err = |text: &str| -> String {
            match toml::from_str::<Scene>(text) {
                Err(e) => e.to_string(),
                Ok(s) => s
                    .disease
                    .unwrap()
                    .resolve(Shape::Anatomical)
                    .unwrap_err()
                    .to_string(),
            }
        };
        let cases = [
            // Unknown keys: serde, with line and column.
            ("[disease]\nkind = \"tumour\"\nsidee = \"left\"\n", "sidee"),
            ("[disease]\nkind = \"appendicitis\"\n", "appendicitis"),
            ("[disease]\nkind = \"tension-pneumothorax\"\nside = \"left\"\n[[disease.events]]\nat_s = 1\nkind = \"tourniquet\"\nside = \"left\"\n", "tourniquet"),
            // Missing and inapplicable keys.
            ("[disease]\nkind = \"closed-pneumothorax\"\nside = \"left\"\n", "index"),
            ("[disease]\nkind = \"closed-pneumothorax\"\nindex = 0.1\n", "side"),
            ("[disease]\nkind = \"closed-pneumothorax\"\nside = \"left\"\nindex = 0.1\ntau = 0.1\n", "tau"),
            ("[disease]\nkind = \"bilateral-pneumothorax\"\nindex_left = 0.1\nindex_right = 0.1\nalpha_ml = 10\n", "alpha_ml"),
            ("[disease]\nkind = \"bilateral-pneumothorax\"\nindex_left = 0.1\n", "index_right"),
            ("[disease]\nkind = \"tumour\"\nside = \"left\"\n", "tumour"),
            ("[disease]\nkind = \"closed-pneumothorax\"\nside = \"left\"\nindex = 0.1\n[[disease.events]]\nat_s = 1\nkind = \"chest-tube\"\nside = \"left\"\n", "events"),
            // Values out of range.
            ("[disease]\nkind = \"closed-pneumothorax\"\nside = \"left\"\nindex = 1.2\n", "index"),
            ("[disease]\nkind = \"closed-pneumothorax\"\nside = \"left\"\nindex = 0.1\nalpha_ml = -5\n", "alpha_ml"),
            ("[disease]\nkind = \"closed-pneumothorax\"\nside = \"left\"\nindex = 0.1\nphi = 3\n", "phi"),
            ("[disease]\nkind = \"bilateral-pneumothorax\"\nindex_left = 0.1\nindex_right = -0.1\n", "index_right"),
            ("[disease]\nkind = \"tension-pneumothorax\"\nside = \"left\"\nv_p_ml = 0\n", "v_p_ml"),
            ("[disease]\nkind = \"tension-pneumothorax\"\nside = \"left\"\ntau = -1\n", "tau"),
            ("[disease]\nkind = \"tension-pneumothorax\"\nside = \"left\"\nbeta_mm = 0\n", "beta_mm"),
            ("[disease]\nkind = \"tension-pneumothorax\"\nside = \"left\"\nv1_max_ml = -3\n", "v1_max_ml"),
            ("[disease]\nkind = \"tension-pneumothorax\"\nside = \"left\"\nv2_max_ml = 1e9\n", "v2_max_ml"),
            ("[disease]\nkind = \"tension-pneumothorax\"\nside = \"left\"\nonset_s = -1\n", "onset_s"),
            ("[disease]\nkind = \"tension-pneumothorax\"\nside = \"left\"\nneedle_vent_cycles = 0\n", "needle_vent_cycles"),
            ("[disease]\nkind = \"tension-pneumothorax\"\nside = \"left\"\nneedle_residual = 2\n", "needle_residual"),
            ("[disease]\nkind = \"tension-pneumothorax\"\nside = \"left\"\nchest_tube_ml_per_cycle = -1\n", "chest_tube_ml_per_cycle"),
            ("[disease]\nkind = \"tension-pneumothorax\"\nside = \"left\"\nonset_s = 50\n[[disease.events]]\nat_s = 10\nkind = \"chest-tube\"\nside = \"left\"\n", "onset_s"),
            ("[disease]\nkind = \"tension-pneumothorax\"\nside = \"left\"\n[[disease.events]]\nat_s = -1\nkind = \"chest-tube\"\nside = \"left\"\n", "at_s"),
            ("[disease]\nkind = \"tumour\"\nside = \"left\"\n[disease.tumour]\ncentre = [0.5, 0.5, 1.5]\nradii_mm = [10, 10, 10]\n", "centre"),
            ("[disease]\nkind = \"tumour\"\nside = \"left\"\n[disease.tumour]\ncentre = [0.5, 0.5, 0.5]\nradii_mm = [10, 0, 10]\n", "radii_mm"),
            ("[disease]\nkind = \"tumour\"\nside = \"left\"\n[disease.tumour]\ncentre = [0.5, 0.5, 0.5]\nradii_mm = [10, 10, 10]\nexpandability = 0\n", "expandability"),
            ("[disease]\nkind = \"tumour\"\nside = \"left\"\n[disease.tumour]\ncentre = [0.5, 0.5, 0.5]\nradii_mm = [10, 10, 10]\nradius = 3\n", "radius"),
            // The model key (issue 25).
            ("[disease]\nkind = \"closed-pneumothorax\"\nside = \"left\"\nindex = 0.1\nmodel = \"textbook\"\n", "textbook"),
            ("[disease]\nkind = \"closed-pneumothorax\"\nside = \"left\"\nindex = 0.1\nmodel = 1\n", "model"),
            ("[disease]\nkind = \"tumour\"\nside = \"left\"\nmodel = \"seed\"\n[disease.tumour]\ncentre = [0.5, 0.5, 0.5]\nradii_mm = [10, 10, 10]\n", "model"),
            ("[disease]\nkind = \"closed-pneumothorax\"\nside = \"left\"\nindex = 0.1\nneedle_tau_cycles = 1\n", "needle_tau_cycles"),
            ("[disease]\nkind = \"tension-pneumothorax\"\nside = \"left\"\nneedle_residual = 0.5\n", "model = \"seed\" only"),
            ("[disease]\nkind = \"tension-pneumothorax\"\nside = \"left\"\nmodel = \"clinical\"\nneedle_vent_cycles = 5\n", "needle_vent_cycles"),
            ("[disease]\nkind = \"tension-pneumothorax\"\nside = \"left\"\nmodel = \"seed\"\nneedle_tau_cycles = 2\n", "model = \"clinical\" only"),
            ("[disease]\nkind = \"tension-pneumothorax\"\nside = \"left\"\nmodel = \"seed\"\nmediastinal_compliance_ml_per_cmh2o = 5\n", "mediastinal_compliance_ml_per_cmh2o"),
            ("[disease]\nkind = \"tension-pneumothorax\"\nside = \"left\"\nmediastinal_compliance_ml_per_cmh2o = 0\n", "mediastinal_compliance_ml_per_cmh2o"),
            ("[disease]\nkind = \"tension-pneumothorax\"\nside = \"left\"\nneedle_tau_cycles = -1\n", "needle_tau_cycles"),
            ("[disease]\nkind = \"tension-pneumothorax\"\nside = \"left\"\nneedle_tau_cycles = nan\n", "needle_tau_cycles"),
        ];
        for (text, key) in cases {
            let e = err(text);
            assert!(e.contains(key), "{key}: {e}");
        }
        // The parser's errors carry the line.
        let e = err("[disease]\nkind = \"tumour\"\nsidee = \"left\"\n");
        assert!(e.contains("line 3"), "{e}");
    }

    #[test]
    fn the_model_key_defaults_to_clinical_and_reaches_the_seed_reading() {
        let closed = |extra: &str| {
            disease(&format!(
                "[disease]\nkind = \"closed-pneumothorax\"\nside = \"left\"\nindex = 0.1\n{extra}"
            ))
            .resolve(Shape::Anatomical)
            .unwrap()
        };
        let DiseaseSpec::Closed(c) = closed("") else {
            panic!("closed")
        };
        assert_eq!(c.model, CourseModel::Clinical);
        let DiseaseSpec::Closed(c) = closed("model = \"seed\"\n") else {
            panic!("closed")
        };
        assert_eq!(c.model, CourseModel::Seed);
        let tension = |extra: &str| {
            let d = disease(&format!(
                "[disease]\nkind = \"tension-pneumothorax\"\nside = \"left\"\n{extra}"
            ));
            match d.resolve(Shape::Anatomical).unwrap() {
                DiseaseSpec::Tension { params, .. } => params,
                _ => panic!("tension"),
            }
        };
        let p = tension("mediastinal_compliance_ml_per_cmh2o = 20\nneedle_tau_cycles = 0.5\n");
        assert_eq!(p.model, CourseModel::Clinical);
        assert_eq!(
            (p.mediastinal_compliance_ml_per_cmh2o, p.needle_tau_cycles),
            (20.0, 0.5)
        );
        let p = tension("model = \"seed\"\nneedle_vent_cycles = 4\nneedle_residual = 0.5\n");
        assert_eq!(
            (p.model, p.needle_vent_cycles, p.needle_residual),
            (CourseModel::Seed, 4, 0.5)
        );
        let d = disease("[disease]\nkind = \"bilateral-pneumothorax\"\nindex_left = 0.1\nindex_right = 0.2\nmodel = \"seed\"\n");
        assert!(
            matches!(d.resolve(Shape::Anatomical).unwrap(), DiseaseSpec::Closed(c) if c.model == CourseModel::Seed)
        );
    }

    #[test]
    fn a_scene_without_disease_is_unchanged_and_round_trips() {
        assert_eq!(Scene::parse("", "empty").unwrap().disease, None);
        let d =
            disease("[disease]\nkind = \"closed-pneumothorax\"\nside = \"left\"\nindex = 0.1\n");
        let text = toml::to_string(&Scene {
            disease: Some(d.clone()),
            ..Scene::default()
        })
        .unwrap();
        assert_eq!(toml::from_str::<Scene>(&text).unwrap().disease, Some(d));
    }

    /// EQUATIONS §4.7: on a recorded breath α is 0 and the keys that shape a spontaneous breath are
    /// refused by name, as is a closed pneumothorax with no lung left to ventilate.
    #[test]
    fn a_ventilated_course_drops_alpha_and_refuses_what_shapes_a_spontaneous_breath() {
        let both = [Side::Right, Side::Left];
        let d = disease("[disease]\nkind = \"tension-pneumothorax\"\nside = \"left\"\n");
        let DiseaseSpec::Tension { params, .. } =
            d.validate_ventilated(&both, Shape::Anatomical).unwrap()
        else {
            panic!("tension")
        };
        assert_eq!(params.alpha_ml, 0.0);
        let d = disease("[disease]\nkind = \"closed-pneumothorax\"\nside = \"left\"\nindex = 1\n");
        assert!(
            matches!(d.validate_ventilated(&both, Shape::Anatomical).unwrap(), DiseaseSpec::Closed(c) if c.alpha_ml == 0.0)
        );
        // The same lung alone: nothing is left to take the recorded volume.
        let e = d
            .validate_ventilated(&[Side::Left], Shape::Anatomical)
            .unwrap_err()
            .to_string();
        assert!(e.contains("index") && e.contains("no lung is left"), "{e}");
        let e = disease(
            "[disease]\nkind = \"bilateral-pneumothorax\"\nindex_left = 1\nindex_right = 1\n",
        )
        .validate_ventilated(&both, Shape::Anatomical)
        .unwrap_err()
        .to_string();
        assert!(e.contains("no lung is left"), "{e}");
        // One lung of two at index 1 is a ventilated lung's ordinary complete collapse.
        disease(
            "[disease]\nkind = \"bilateral-pneumothorax\"\nindex_left = 1\nindex_right = 0.5\n",
        )
        .validate_ventilated(&both, Shape::Anatomical)
        .unwrap();
        for (text, key) in [
            (
                "kind = \"closed-pneumothorax\"\nside = \"left\"\nindex = 0.1\nalpha_ml = 100\n",
                "alpha_ml",
            ),
            (
                "kind = \"tension-pneumothorax\"\nside = \"left\"\nalpha_ml = 0\n",
                "alpha_ml",
            ),
            (
                "kind = \"tension-pneumothorax\"\nside = \"left\"\nphi = 0.1\n",
                "phi",
            ),
            (
                "kind = \"tumour\"\nside = \"right\"\n[disease.tumour]\ncentre = [0.6, 0.3, 0.8]\n\
                 radii_mm = [15, 15, 15]\nresistance_phi = 0.1\n",
                "tumour.resistance_phi",
            ),
        ] {
            let d = disease(&format!("[disease]\n{text}"));
            d.validate(&both, Shape::Anatomical).unwrap();
            let e = d
                .validate_ventilated(&both, Shape::Anatomical)
                .unwrap_err()
                .to_string();
            assert!(e.starts_with(&format!("[disease] {key}:")), "{e}");
        }
        // The scene refuses them when loaded with a waveform, and takes the rest.
        let scene = |disease: &str| {
            toml::from_str::<Scene>(&format!("[pv]\nwaveform = \"r.csv\"\n[disease]\n{disease}"))
                .unwrap()
        };
        let s = scene("kind = \"tension-pneumothorax\"\nside = \"left\"\nphi = 0.1\n");
        assert!(s.validate().unwrap_err().to_string().contains("phi"));
        let s = scene("kind = \"tension-pneumothorax\"\nside = \"left\"\n");
        assert!(
            matches!(s.disease_spec(), Ok(Some(DiseaseSpec::Tension { params, .. })) if params.alpha_ml == 0.0)
        );
    }
}
