//! # lungdyn-launcher: running lungdyn, measuring it and deploying it
//!
//! The `lungdyn` command line (`cli/`) is a thin front over this library and `lung-bake`'s tools:
//! * a run's stages — [`demo::run_watched`]: validate the arguments, resolve the scene, prepare its
//!   kernels ([`prepare`]: bake what is missing, once), start each role from one role table
//!   ([`launch`]), watch (drain the streams, [`supervise`]: restart a process that dies or stops
//!   answering), then the pictures ([`strip`], [`record`]) and the report ([`stats`]); the instance
//!   lock folder read as untrusted input ([`instances`]) and the run's output folder ([`outputs`]);
//! * the harnesses that are thin users of those stages: [`latency`] (per-hop latency against the
//!   display schedule), [`faults`] (injected faults and their recovery);
//! * the headless engine run and the scene checks ([`scene_check`]), a trainee's events into a
//!   running scene ([`scene_event`]);
//! * the speed–accuracy trade-off evaluator ([`tradeoff`]), a respiratory recording followed as
//!   if live against its hindsight volume ([`breathing_check`]), and the plots ([`plot`]); the input
//!   options every command that reads files takes ([`input_args`]);
//! * a breath out of lungdyn: [`export`] (one breath as glTF for any viewer);
//! * deployment: [`install`] (thin role binaries, units, udev rule) and [`doctor`] (what this machine
//!   can run); [`rig_json`], the rig's files as the reports show them.

pub mod breathing_check;
pub mod breathing_follow;
pub mod breathing_sites;
pub mod demo;
pub mod doctor;
pub mod export;
pub mod faults;
pub mod input_args;
pub mod install;
pub mod instances;
pub mod latency;
pub mod launch;
pub mod outputs;
pub mod plot;
pub mod prepare;
pub mod record;
pub mod rig_json;
pub mod scene_check;
pub mod scene_event;
pub mod slicer;
pub mod stats;
pub mod strip;
pub mod supervise;
pub mod tradeoff;
