//! # lung-model: the lung as the run time holds it
//!
//! What the engine and the renderer load and share — and nothing that bakes or fits (that is
//! `lung-bake`, which the run-time processes do not link):
//! * [`mesh`] — the triangle surface type, its checks (closed, 2-manifold, wound outwards), the
//!   procedural default lungs, OBJ/PLY export and atomic writes;
//! * [`kernel`] — the kernel file: format, verified memory-mapped reading, identity, raw writing;
//! * [`operator`] — the transfer operator as stored (CSR rows of eq. 6.1), eq. 7.1's gather and the
//!   elasticity field that shaped it;
//! * [`deform`] — per-vertex displacement (eq. 6.14–6.18), the volume cubic, [`deform::LungModel`],
//!   and the four deformation modes on the CPU with their volume forms ([`deform::modes`]);
//! * [`frame`] — the body frame's handedness and the one reflection between it and the room (RAS);
//! * [`orientation`] — the patient's pose → gravity in the body frame → the applied force's weights
//!   (exact, and the seed's eq. 7.8–7.9 blend); [`sh`] — real spherical harmonics and projection
//!   (seed ch. 7);
//! * [`pv`] — the pressure–volume forward model (seed ch. 5, eq. 2.12–2.16, 5.11), presets and the
//!   constants files a scene loads;
//! * [`disease`] — the seed's disease states (chapter 8): closed and tension pneumothorax with
//!   interventions, tumour-influenced lungs;
//! * [`scene`] — what the physics makes of a scene (`SceneExt`: reading, checking, the lungs' models,
//!   the PV model or recording; the schema is `lungdyn-scene`'s; [`scene_disease`]: its `[disease]` table);
//! * [`breathing`] — a live respiratory signal followed: calibrated to volume, predicted to the
//!   display time, breaths and pauses found (issue 35; beyond the seed, §7.5);
//! * [`input`] — bounded reading of every input file; [`plausible`] — the physical ranges every input
//!   is checked against, with their sources.

// `!(x > 0.0)` is how this crate refuses NaN together with out-of-range values; keep it.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod breathing;
pub mod deform;
pub mod disease;
pub mod frame;
pub mod input;
pub mod kernel;
pub mod mesh;
pub mod operator;
pub mod orientation;
pub mod plausible;
pub mod pv;
pub mod recording;
pub mod scene;
pub mod scene_disease;
/// The `[remote]` table (`lungdyn_scene::remote`, under its old name).
pub use lungdyn_scene::remote as scene_remote;
pub mod sh;
pub mod units;
