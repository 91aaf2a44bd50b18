//! # lung-bake: everything done before a run
//!
//! Used by `lungdyn bake`, `fit-motion`, `pv fit`, `mesh check` and the launcher (which bakes the
//! default lungs once and hands every process the same kernel file); never linked by the engine or
//! renderer processes.
//! * [`import`] — OBJ/PLY/STL import with welding and safe repairs, bounded reading, and the size of
//!   a lung in the stated unit; [`surface_checks`] — shells, self-intersections, degenerate
//!   triangles and which lung the geometry is;
//! * [`operator`] — the node graph (eq. 6.7) and the pitcher–catcher pass (eq. 6.11–6.13);
//! * [`kernel`] — the whole of seed ch. 6 for one lung, written as a kernel file; [`orient`] — what the
//!   orientation-following modes of seed ch. 7 need (basis responses, spherical-harmonic transfer
//!   coefficients and `α`, volume forms) and their errors against eq. 7.1;
//! * [`motion_fit`] and [`surface_fit`] — the motion constants from landmarks or surfaces (§6.4.2);
//!   [`motion_models`] — the power law, polynomial and thin-plate fields compared on held-out
//!   landmarks, with the complexity chosen by inner cross-validation; [`landmarks`] — reading points
//!   in a stated coordinate frame (body, LPS, RAS, voxel indices, DIR-Lab files);
//! * [`pv`] — reading measured PV curves and fitting eq. 5.11 to them (§5.3.5);
//! * [`lsq`] — the least-squares wrapper both fits use;
//! * [`mask`] — a patient's lung surface (and lobes) from a CT lung segmentation (NIfTI, NRRD,
//!   MetaImage).

// `!(x > 0.0)` is how this crate refuses NaN together with out-of-range values; keep it.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod folds;
pub mod import;
pub mod kernel;
pub mod landmarks;
pub mod lsq;
pub mod mask;
pub mod motion_fit;
pub mod motion_models;
pub mod operator;
pub mod orient;
pub mod patient_motion;
pub mod pv;
pub mod smooth;
pub mod surface_checks;
pub mod surface_fit;
pub mod tri_intersect;
pub mod tumour;
pub mod unfitted;
