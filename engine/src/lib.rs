//! # engine: lungdyn's physics and its deterministic tick
//!
//! Stages, each a module named after it:
//! * [`pv`] — the pressure–volume relation (seed ch. 5, eq. 2.12–2.16, 5.11);
//! * [`mesh`] — lung surfaces: the procedural default lungs, checks, export;
//! * [`deform`] — per-vertex displacement (seed ch. 6, eq. 6.14–6.16, 6.18);
//! * [`runtime`] — the fixed-tick engine loop and its pure core;
//! * [`scene`] — what a run models.
//!
//! Binaries are thin: `engine` (the process) and `lungdyn` (the launcher, in `cli/`) only parse
//! arguments and call into this library.

pub mod deform;
pub mod mesh;
pub mod pv;
pub mod runtime;
pub mod scene;
