//! # unfitted: the motion a patient's lung is baked with when it has no fit it can draw
//!
//! A lung made from a patient's mask (`lungdyn patient`) without a breath-hold pair, or whose motion
//! fitted to the pair folds the surface within the lung's share of a tidal breath, still breathes,
//! and its motion must beat doing nothing (issue 34). Two motions are at hand:
//!
//! * the **built-in population** (`directions = "population"`: eq. 6.14–6.18 with constants matched
//!   to DIR-Lab's 4DCT landmarks on the generated lungs, EQUATIONS.md §2.4). On the six shared
//!   COPDgene breath-hold pairs it lands farther from the inhale surface than leaving the lung
//!   still on 10 of 12 lungs (docs/masks/breath_hold_baselines.md);
//! * the **breath-hold population** (`directions = "breath-hold"`: the mean of the six patients'
//!   fitted direction and force fields, scale-free, `bench/population_motion.py`). Judged
//!   leave-one-patient-out it beats no motion and uniform scaling on all 12 lungs
//!   (docs/masks/population_motion_table.md). It folds the generated lungs, whose mediastinal face
//!   differs from the patients', so it is not the generated lungs' default.
//!
//! A patient's lung gets the breath-hold population where it draws the lung's share of a tidal
//! breath without a fold (checked on the baked kernel, as the GPU draws it), the built-in motion
//! otherwise, and says which.

use lung_model::deform::DirectionPreset;
use lung_model::kernel::BakeSettings;
use lung_model::mesh::{Side, TriMesh};

use crate::kernel::{BakeError, Kernel};

/// Which motion to bake without a fit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Choice {
    /// The breath-hold population where it draws the tidal share without a fold, else the built-in.
    Auto,
    /// The breath-hold population, whatever it draws.
    BreathHold,
    /// The built-in population.
    Builtin,
}

/// The motion baked.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Baked {
    /// The breath-hold population.
    BreathHold,
    /// The breath-hold population, asked for, though it folds within the tidal share.
    BreathHoldFolds,
    /// The built-in population, asked for.
    Builtin,
    /// The built-in population, because the breath-hold population folds within the tidal share.
    BuiltinBreathHoldFolds,
}

impl Baked {
    /// What a report says of it; `fit_folds` when a fit to the pair was made and not kept.
    pub fn describe(self, fit_folds: bool) -> &'static str {
        match (self, fit_folds) {
            (Baked::BreathHold, false) => "breath-hold population",
            (Baked::BreathHold, true) => {
                "breath-hold population (the fitted motion folds within a tidal breath)"
            }
            (Baked::BreathHoldFolds, _) => {
                "breath-hold population, as asked, though it folds within a tidal breath"
            }
            (Baked::Builtin, false) => "built-in population",
            (Baked::Builtin, true) => {
                "built-in population (the fitted motion folds within a tidal breath)"
            }
            (Baked::BuiltinBreathHoldFolds, false) => {
                "built-in population (the breath-hold population folds within a tidal breath)"
            }
            (Baked::BuiltinBreathHoldFolds, true) => {
                "built-in population (the fitted motion and the breath-hold population fold within \
                 a tidal breath)"
            }
        }
    }
}

/// A lung baked without a fit.
#[derive(Debug)]
pub struct Unfitted {
    /// The kernel.
    pub kernel: Kernel,
    /// Its motion.
    pub motion: Baked,
    /// With the breath-hold population tried: how far above the exhale volume it draws no fold (ml,
    /// to 1/768 of the tidal share; the share itself when it does not fold within it).
    pub breath_hold_fold_free_ml: Option<f64>,
}

/// Bakes `mesh` (a patient's lung, at its exhale volume) with the motion `choice` picks for a lung
/// breathing `share_ml` above it; `progress` counts transfer rows, `say` tells a person each step.
pub fn bake(
    side: Side,
    mesh: &TriMesh,
    share_ml: f64,
    choice: Choice,
    progress: &(dyn Fn(usize) + Sync),
    say: &dyn Fn(&str),
) -> Result<Unfitted, BakeError> {
    let builtin = |motion| -> Result<Unfitted, BakeError> {
        let settings = BakeSettings::for_preset(DirectionPreset::Population, side);
        Ok(Unfitted {
            kernel: crate::kernel::bake(side, mesh.clone(), &settings, progress)?,
            motion,
            breath_hold_fold_free_ml: None,
        })
    };
    if choice == Choice::Builtin {
        return builtin(Baked::Builtin);
    }
    let settings = BakeSettings::for_preset(DirectionPreset::BreathHold, side);
    let kernel = crate::kernel::bake(side, mesh.clone(), &settings, progress)?;
    let model = lung_model::deform::LungModel::from_unit_displacement(
        side,
        kernel.mesh.clone(),
        kernel.unit_displacement.clone(),
    );
    let free = crate::patient_motion::fold_free_ml(&model, share_ml);
    let folds = free < share_ml;
    if folds {
        say(&format!(
            "the breath-hold population folds the {} lung from +{free:.0} ml, within its tidal share \
             of {share_ml:.0} ml",
            side.name()
        ));
    }
    if folds && choice == Choice::Auto {
        say("baking the built-in population motion instead");
        let mut out = builtin(Baked::BuiltinBreathHoldFolds)?;
        out.breath_hold_fold_free_ml = Some(free);
        return Ok(out);
    }
    Ok(Unfitted {
        kernel,
        motion: if folds {
            Baked::BreathHoldFolds
        } else {
            Baked::BreathHold
        },
        breath_hold_fold_free_ml: Some(free),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lung() -> TriMesh {
        lung_model::mesh::anatomy::lung(Side::Right, 1_500).unwrap()
    }

    fn breath_hold_field(k: &Kernel) -> bool {
        let population = BakeSettings::for_preset(DirectionPreset::BreathHold, Side::Right);
        k.meta.settings.force_field.is_some()
            && k.meta.settings.force_field == population.force_field
            && k.meta.settings.direction_field == population.direction_field
    }

    /// Each choice bakes the motion it names, and "auto" takes the breath-hold population exactly
    /// when it draws the share without a fold (the share past its fold-free range: the built-in).
    #[test]
    fn auto_takes_the_breath_hold_population_only_where_it_draws_the_share() {
        let mesh = lung();
        let said = std::cell::RefCell::new(Vec::<String>::new());
        let say = |s: &str| said.borrow_mut().push(s.to_string());
        let built = bake(Side::Right, &mesh, 250.0, Choice::Builtin, &|_| {}, &say).unwrap();
        assert_eq!(built.motion, Baked::Builtin);
        assert!(built.kernel.meta.settings.force_field.is_none());
        assert_eq!(built.breath_hold_fold_free_ml, None);
        // Far past any breath (3 l into one lung): the population folds there, and says so when
        // asked for anyway.
        let deep = 3_000.0;
        let forced = bake(Side::Right, &mesh, deep, Choice::BreathHold, &|_| {}, &say).unwrap();
        assert_eq!(forced.motion, Baked::BreathHoldFolds);
        assert!(breath_hold_field(&forced.kernel));
        let free = forced.breath_hold_fold_free_ml.unwrap();
        assert!(
            free > 0.0 && free < deep,
            "fold-free to {free} of {deep} ml"
        );
        assert!(said
            .borrow()
            .iter()
            .any(|s| s.contains("folds the right lung")));
        let auto = bake(Side::Right, &mesh, deep, Choice::Auto, &|_| {}, &say).unwrap();
        assert_eq!(auto.motion, Baked::BuiltinBreathHoldFolds);
        assert!(auto.kernel.meta.settings.force_field.is_none());
        assert_eq!(auto.breath_hold_fold_free_ml, Some(free));
        // Within the fold-free range: the population, and nothing said.
        said.borrow_mut().clear();
        let within = 0.5 * free;
        let auto = bake(Side::Right, &mesh, within, Choice::Auto, &|_| {}, &say).unwrap();
        assert_eq!(auto.motion, Baked::BreathHold);
        assert!(breath_hold_field(&auto.kernel));
        assert_eq!(auto.breath_hold_fold_free_ml, Some(within));
        assert!(said.borrow().is_empty(), "{:?}", said.borrow());
    }
}
