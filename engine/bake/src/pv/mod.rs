//! The PV relation at bake time: reading measured curves ([`curve`]) and fitting the control
//! function of eq. 5.11 to them ([`fit`], seed §5.3.5, EQUATIONS §1.2).

pub mod curve;
pub mod fit;
pub mod recording;
