//! # tracker-pose: what becomes of tracked poses after the bridge
//!
//! * [`registration`] — the lungs' model frame onto the patient reference from corresponding
//!   fiducials (Horn/Umeyama, FRE, collinearity);
//! * [`calib`] — the calibration file `lungdyn register` writes and its checked loader;
//! * [`optics`] — the HMD optics file (IPD, per-eye offsets, projection) and its checked loader;
//! * [`predict`] — pose prediction to the display time and its evaluation on recorded motion.
//!
//! Pure computation and small checked file formats, no tracker I/O: the renderer can use it without
//! linking the bridge's sources (serial ports, sockets).

pub mod calib;
pub mod optics;
pub mod predict;
pub mod registration;
