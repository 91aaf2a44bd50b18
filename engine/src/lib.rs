//! # engine: lungdyn's physics and its deterministic tick
//!
//! Stages, each a module named after it:
//! * [`pv`] — the pressure–volume relation (seed ch. 5, eq. 2.12–2.16, 5.11);
//! * [`mesh`] — lung surfaces: the procedural default lungs, checks, export;
//! * [`operator`] — the Green's-function transfer operator (seed §6.2–6.3, eq. 6.7–6.13);
//! * [`deform`] — per-vertex displacement (seed ch. 6, eq. 6.14–6.16, 6.18);
//! * [`kernel`] — baking a lung (ch. 6 end to end) and the memory-mapped kernel file;
//! * [`motion_fit`] — c1..c6 of eq. 6.14–6.16 from corresponding points (seed §6.4.2);
//! * [`surface_fit`] — the same constants from a second-phase surface without correspondences;
//! * [`runtime`] — the fixed-tick engine loop and its pure core;
//! * [`scene`] — what a run models.
//!
//! Binaries are thin: `engine` (the process) and `lungdyn` (the launcher, in `cli/`) only parse
//! arguments and call into this library.

// `!(x > 0.0)` is how this crate refuses NaN together with out-of-range values; keep it.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod deform;
pub mod kernel;
pub mod lsq;
pub mod mesh;
pub mod motion_fit;
pub mod operator;
pub mod pv;
pub mod runtime;
pub mod scene;
pub mod surface_fit;
