//! # engine: lungdyn's deterministic tick
//!
//! [`runtime::EngineCore`] turns the scene's PV model and each lung's kernel into one
//! [`ipc_types::EngineFrame`] per tick — per-lung volume, breathing phase and cycle, deformation
//! scale, rigid offset, the kernel's identity — as a pure function of its inputs;
//! [`runtime::process`] paces it on the tracker stream and publishes. The lung model it reads is
//! `lung-model`; it never bakes (`lung-bake`) and links none of the fitting or import code.
//!
//! [`headless`] runs the same tick function without processes (`lungdyn scene run`).
//!
//! The binary (`engine`, and `lungdyn engine`) only parses arguments and calls [`runtime::run`].

pub mod headless;
pub mod runtime;
