//! # lungdyn: the launcher and command-line tools
//!
//! `lungdyn demo` supervises the three processes and measures them ([`demo`], [`stats`]);
//! `lungdyn mesh generate` writes the built-in lungs ([`mesh_cmd`]). The process roles themselves
//! (`lungdyn tracker-bridge|engine|renderer`) are the same library entry points as the standalone
//! binaries.

pub mod bake_cmd;
pub mod demo;
pub mod doctor;
pub mod faults;
pub mod input_args;
pub mod install;
pub mod instances;
pub mod kernel_plot;
pub mod latency;
pub mod launch;
pub mod mask_cmd;
pub mod mesh_cmd;
pub mod motion_cmd;
pub mod motion_input;
pub mod motion_plot;
pub mod motion_report;
pub mod outputs;
pub mod pair_cmd;
pub mod patient_cmd;
pub mod plot;
pub mod prepare;
pub mod pv_cmd;
pub mod pv_recording;
pub mod record;
pub mod register_cmd;
pub mod scene_check;
pub mod scene_event;
pub mod stats;
pub mod strip;
pub mod supervise;
pub mod tracker_cmd;
pub mod tradeoff;
