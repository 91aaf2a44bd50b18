//! # lungdyn: the command line
//!
//! `main.rs` parses the commands and hands each to a library: the launcher's (`lungdyn demo`,
//! `latency`, `faults`, `scene check|run|prepare|event`, `install`, `doctor`, `bench tradeoff`) to
//! `lungdyn-launcher`, re-exported here under their module names; the tools over `lung-bake`
//! (bake, meshes, masks, motion fits, a patient, PV) and the tracker's and the rig's tools are the
//! modules here. The process roles themselves (`lungdyn tracker-bridge|engine|renderer`) are the same
//! library entry points as the standalone binaries.

pub mod bake_cmd;
pub mod kernel_plot;
pub mod mask_cmd;
pub mod mesh_cmd;
pub mod motion_cmd;
pub mod motion_input;
pub mod motion_plot;
pub mod motion_report;
pub mod pair_cmd;
pub mod patient_cmd;
pub mod pv_cmd;
pub mod pv_recording;
pub mod register_cmd;
pub mod tracker_cmd;

pub use lungdyn_launcher::{
    breathing_check, breathing_follow, breathing_sites, demo, doctor, export, faults, input_args,
    install, instances, latency, launch, outputs, plot, prepare, record, scene_check, scene_event,
    slicer, stats, strip, supervise, tradeoff,
};
