//! # disease: the seed's disease states (chapter 8) as pure, deterministic functions
//!
//! Work in progress: the breathing-resistance changes (eq. 8.8–8.9, [`resistance`]) and the
//! collapsing lung's shape ([`collapse`]).

pub mod collapse;
pub mod resistance;
