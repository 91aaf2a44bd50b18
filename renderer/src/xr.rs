//! OpenXR output, the pure parts: what the runtime-facing code ([`crate::xr_runtime`], behind the
//! `openxr` cargo feature) decides with, kept free of the runtime so it is tested everywhere.
//!
//! * Each eye's projection from the runtime's `XrFovf` (four angles, radians, left and down
//!   negative), in the renderer's clip space (right-handed, looking along −Z, depth 0 at near .. 1
//!   at far), and each eye's pose in the head (`XR_REFERENCE_SPACE_TYPE_VIEW`, metres) as the
//!   eye → HMD transform in millimetres: together an [`HmdEyes`], drawn by the same rig as an
//!   optics file (the external tracker still gives the HMD's pose on the patient).
//! * `XrTime` ↔ CLOCK_MONOTONIC: OpenXR times are nanoseconds on the runtime's own clock;
//!   `XR_KHR_convert_timespec_time` converts a `timespec` of CLOCK_MONOTONIC to it. [`XrClock`] keeps
//!   the offset from one such pair, so the predicted display time becomes an instant on the clock
//!   the tracker samples are stamped with ([`crate::predict::HmdPredictor::pose_at_display`]).
//! * The environment blend mode: additive where the runtime offers it (an optical see-through
//!   headset: black shows the patient, light adds to the view), else opaque, else alpha blend.
//! * The swapchain format: the renderer's own sRGB RGBA8 where the runtime offers it, else the
//!   first of the runtime's formats (its preference order) the present pass can draw into; the
//!   frame is drawn 1:1 into the swapchain image, the eyes side by side as drawn.

use glam::{Mat4, Quat, Vec3};

use lung_model::scene::Look;

use crate::camera::HmdEyes;

/// An eye's field of view as OpenXR gives it (`XrFovf`): angles from the view direction, radians;
/// left and down are negative for a frustum that contains the view direction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fov {
    /// Angle of the left edge (negative to the left).
    pub left: f32,
    /// Angle of the right edge.
    pub right: f32,
    /// Angle of the top edge.
    pub up: f32,
    /// Angle of the bottom edge (negative below).
    pub down: f32,
}

/// Largest half-angle accepted, radians (just under 90°: the tangent stays finite).
const MAX_ANGLE: f32 = 1.55;

impl Fov {
    /// The frustum's tangents `[left, right, down, up]`, measured outwards (as an optics file's
    /// `frustum_tan`); `None` for a degenerate or non-finite field of view (a runtime's bad value
    /// must never reach a frame).
    pub fn tangents(&self) -> Option<[f64; 4]> {
        let ok = |a: f32| a.is_finite() && a.abs() < MAX_ANGLE;
        if !(ok(self.left) && ok(self.right) && ok(self.up) && ok(self.down)) {
            return None;
        }
        if self.right <= self.left || self.up <= self.down {
            return None;
        }
        let t = |a: f32| (a as f64).tan();
        Some([-t(self.left), t(self.right), -t(self.down), t(self.up)])
    }

    /// The projection in the renderer's clip space with near and far planes in mm.
    pub fn projection(&self, near_mm: f64, far_mm: f64) -> Option<Mat4> {
        let t = self.tangents()?;
        Some(Mat4::from_cols_array_2d(
            &tracker_pose::optics::frustum_projection(t, near_mm, far_mm),
        ))
    }
}

/// One eye as the runtime locates it in the head's space (`XR_REFERENCE_SPACE_TYPE_VIEW`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct XrEye {
    /// Position, metres (OpenXR's unit).
    pub position_m: [f32; 3],
    /// Orientation, unit quaternion `[x, y, z, w]`.
    pub orientation: [f32; 4],
    /// Field of view.
    pub fov: Fov,
}

impl XrEye {
    /// Eye → head rotation and position (mm); `None` for a non-finite pose or a non-unit
    /// quaternion.
    pub fn to_head_mm(&self) -> Option<(Quat, Vec3)> {
        let p = Vec3::from(self.position_m) * 1000.0;
        let q = Quat::from_array(self.orientation);
        if !(p.is_finite() && q.is_finite() && (q.length() - 1.0).abs() < 1e-3) {
            return None;
        }
        Some((q.normalize(), p))
    }
}

/// Both eyes of the runtime as the rig's [`HmdEyes`], each `width`×`height` pixels (the
/// runtime's recommended image size), clipped at `near_mm`/`far_mm`. `None` when either eye's
/// pose or field of view is unusable (the frame then keeps the previous eyes).
pub fn hmd_eyes(
    eyes: &[XrEye; 2],
    width: u32,
    height: u32,
    near_mm: f64,
    far_mm: f64,
) -> Option<HmdEyes> {
    let to_hmd = [eyes[0].to_head_mm()?, eyes[1].to_head_mm()?];
    let tangents = [eyes[0].fov.tangents()?, eyes[1].fov.tangents()?];
    Some(HmdEyes::from_eyes(
        to_hmd, tangents, near_mm, far_mm, width, height,
    ))
}

/// `XrTime` ↔ CLOCK_MONOTONIC, from one pair of readings of the same instant.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct XrClock {
    /// XrTime minus monotonic ns.
    offset_ns: i128,
}

impl XrClock {
    /// From the runtime's time `xr_time` of the monotonic instant `monotonic_ns`.
    pub fn from_pair(xr_time: i64, monotonic_ns: u64) -> Self {
        Self {
            offset_ns: xr_time as i128 - monotonic_ns as i128,
        }
    }

    /// The monotonic instant of `xr_time`; `None` before the monotonic clock's zero or past its
    /// range (never a wrapped value).
    pub fn to_monotonic(&self, xr_time: i64) -> Option<u64> {
        u64::try_from(xr_time as i128 - self.offset_ns).ok()
    }

    /// The XrTime of the monotonic instant `monotonic_ns`; `None` when it does not fit an XrTime
    /// (or is not positive: OpenXR times are).
    pub fn to_xr(&self, monotonic_ns: u64) -> Option<i64> {
        i64::try_from(monotonic_ns as i128 + self.offset_ns)
            .ok()
            .filter(|&t| t > 0)
    }
}

/// A `timespec` (seconds, nanoseconds) as nanoseconds; `None` for a negative or malformed one.
pub fn timespec_ns(sec: i64, nsec: i64) -> Option<u64> {
    if sec < 0 || !(0..1_000_000_000).contains(&nsec) {
        return None;
    }
    (sec as u64)
        .checked_mul(1_000_000_000)?
        .checked_add(nsec as u64)
}

/// Nanoseconds as a `timespec` (seconds, nanoseconds).
pub fn ns_timespec(ns: u64) -> (i64, i64) {
    ((ns / 1_000_000_000) as i64, (ns % 1_000_000_000) as i64)
}

/// A Vulkan API version as `VK_MAKE_API_VERSION(0, major, minor, 0)` encodes it.
pub const fn vk_api_version(major: u32, minor: u32) -> u32 {
    (major << 22) | (minor << 12)
}

/// The Vulkan API version to create the instance with (through the runtime) from the loader's
/// (`vkEnumerateInstanceVersion`): the loader's own, capped at 1.3, as wgpu asks when it makes its
/// instance itself. wgpu takes the GPU's own version as the one in use — it calls a promoted entry
/// point through the core table when the GPU is new enough — so an instance made for an older
/// version than that hands it null entry points (a 1.1 instance on lavapipe's 1.3 aborted in
/// `vkGetSemaphoreCounterValue`). `None` below 1.1, wgpu's minimum.
pub fn vulkan_instance_version(loader: u32) -> Option<u32> {
    let without_variant = loader & 0x1FFF_FFFF;
    (without_variant >= vk_api_version(1, 1)).then(|| without_variant.min(vk_api_version(1, 3)))
}

/// A running minimum, mean and maximum of signed nanosecond intervals (no allocation: kept per
/// frame).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Spread {
    n: u64,
    sum: i128,
    min: i64,
    max: i64,
}

impl Spread {
    /// Add one interval.
    pub fn add(&mut self, ns: i64) {
        if self.n == 0 {
            (self.min, self.max) = (ns, ns);
        }
        self.n += 1;
        self.sum += ns as i128;
        self.min = self.min.min(ns);
        self.max = self.max.max(ns);
    }

    /// How many were added.
    pub fn count(&self) -> u64 {
        self.n
    }

    /// (min, mean, max) in milliseconds; `None` before the first.
    pub fn ms(&self) -> Option<(f64, f64, f64)> {
        (self.n > 0).then(|| {
            (
                self.min as f64 / 1e6,
                self.sum as f64 / self.n as f64 / 1e6,
                self.max as f64 / 1e6,
            )
        })
    }
}

impl std::fmt::Display for Spread {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.ms() {
            Some((lo, mean, hi)) => write!(f, "{mean:.2} ms (min {lo:.2}, max {hi:.2})"),
            None => write!(f, "none"),
        }
    }
}

/// What the renderer gave the runtime over a run (its goodbye line): how many frames it waited
/// for, how many it ended with the projection layer of both eyes or empty, and the intervals the
/// display-time prediction spans.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct XrStats {
    /// `xrWaitFrame` calls that returned a frame.
    pub waited: u64,
    /// Frames ended with the projection layer (both eyes' views).
    pub layers: u64,
    /// Frames ended without a layer (the runtime said not to render, or no views were located).
    pub empty: u64,
    /// Predicted display time minus CLOCK_MONOTONIC when `xrWaitFrame` returned: how far ahead
    /// the HMD pose is predicted for the frame about to be drawn.
    pub lead_at_wait: Spread,
    /// Predicted display time minus CLOCK_MONOTONIC at `xrEndFrame`: negative is a frame submitted
    /// after the instant it was meant to be shown.
    pub lead_at_submit: Spread,
    /// Between successive predicted display times: the runtime's frame period.
    pub period: Spread,
    last_display_ns: Option<u64>,
}

impl XrStats {
    /// A frame waited for, to be shown at `display_ns`, the wait returning at `now_ns` (both
    /// CLOCK_MONOTONIC).
    pub fn waited(&mut self, display_ns: u64, now_ns: u64) {
        self.waited += 1;
        self.lead_at_wait.add(signed_diff(display_ns, now_ns));
        if let Some(last) = self.last_display_ns.replace(display_ns) {
            self.period.add(signed_diff(display_ns, last));
        }
    }

    /// A frame ended at `now_ns`, to be shown at `display_ns`, with the projection layer or not.
    pub fn ended(&mut self, display_ns: Option<u64>, now_ns: u64, with_layer: bool) {
        if with_layer {
            self.layers += 1;
        } else {
            self.empty += 1;
        }
        if let Some(d) = display_ns {
            self.lead_at_submit.add(signed_diff(d, now_ns));
        }
    }
}

impl std::fmt::Display for XrStats {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} frames waited for, {} ended with both eyes' projection layer, {} ended empty; \
             display time ahead of CLOCK_MONOTONIC at xrWaitFrame {}, at xrEndFrame {}; \
             runtime frame period {}",
            self.waited,
            self.layers,
            self.empty,
            self.lead_at_wait,
            self.lead_at_submit,
            self.period
        )
    }
}

/// `a - b` in signed nanoseconds, saturating.
fn signed_diff(a: u64, b: u64) -> i64 {
    let d = a as i128 - b as i128;
    d.clamp(i64::MIN as i128, i64::MAX as i128) as i64
}

/// How the frame composes with the world (`XrEnvironmentBlendMode`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BlendMode {
    /// The frame replaces the world (a VR headset).
    Opaque,
    /// The frame's light adds to the world (optical see-through: black is transparent).
    Additive,
    /// The frame's alpha mixes it with the world (video pass-through).
    AlphaBlend,
}

/// The blend mode to submit with among the runtime's (in its order): additive whenever offered —
/// an optical see-through headset, the overlay's intended display, where the frame must add light
/// to the patient rather than hide them — else opaque, else alpha blend; `None` if it offers none
/// of these.
pub fn choose_blend_mode(offered: &[BlendMode]) -> Option<BlendMode> {
    [
        BlendMode::Additive,
        BlendMode::Opaque,
        BlendMode::AlphaBlend,
    ]
    .into_iter()
    .find(|m| offered.contains(m))
}

/// The look to draw with on a display of blend mode `blend`, the scene's being `look`: on an
/// additive (optical see-through) display whatever is not black adds light over the patient — the
/// opaque and translucent looks' grey background would veil the whole view — so there the look is
/// see-through (black background, lungs that emit light); elsewhere the scene's.
pub fn look_for_blend(blend: BlendMode, look: Look) -> Look {
    match blend {
        BlendMode::Additive => Look::SeeThrough,
        BlendMode::Opaque | BlendMode::AlphaBlend => look,
    }
}

/// Vulkan format codes (`VkFormat`) of the swapchain formats the renderer can fill.
pub mod vk_format {
    /// `VK_FORMAT_R8G8B8A8_UNORM`.
    pub const R8G8B8A8_UNORM: i64 = 37;
    /// `VK_FORMAT_R8G8B8A8_SRGB`: the renderer's own colour format.
    pub const R8G8B8A8_SRGB: i64 = 43;
    /// `VK_FORMAT_B8G8R8A8_UNORM`.
    pub const B8G8R8A8_UNORM: i64 = 44;
    /// `VK_FORMAT_B8G8R8A8_SRGB`.
    pub const B8G8R8A8_SRGB: i64 = 50;
}

/// The wgpu format of a swapchain `VkFormat` the renderer can fill, if any.
pub fn wgpu_format(vk: i64) -> Option<wgpu::TextureFormat> {
    use wgpu::TextureFormat as F;
    match vk {
        vk_format::R8G8B8A8_SRGB => Some(F::Rgba8UnormSrgb),
        vk_format::B8G8R8A8_SRGB => Some(F::Bgra8UnormSrgb),
        vk_format::R8G8B8A8_UNORM => Some(F::Rgba8Unorm),
        vk_format::B8G8R8A8_UNORM => Some(F::Bgra8Unorm),
        _ => None,
    }
}

/// The swapchain format among the runtime's (in its preference order): the renderer's own colour
/// format when offered, else the runtime's first sRGB format we can
/// draw into (the present pass then converts), else its first linear one. `None` when it offers
/// none we can fill.
pub fn choose_swapchain_format(offered: &[i64]) -> Option<(i64, wgpu::TextureFormat)> {
    let own = crate::draw::COLOR_FORMAT;
    let fillable = || offered.iter().filter_map(|&v| Some((v, wgpu_format(v)?)));
    fillable()
        .find(|(_, f)| *f == own)
        .or_else(|| fillable().find(|(_, f)| f.is_srgb()))
        .or_else(|| fillable().next())
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec4;

    fn symmetric(deg: f32) -> Fov {
        let a = deg.to_radians();
        Fov {
            left: -a,
            right: a,
            up: a,
            down: -a,
        }
    }

    /// A point in the eye's frame → normalised device coordinates.
    fn ndc(p: Mat4, v: Vec3) -> Vec3 {
        let c = p * Vec4::new(v.x, v.y, v.z, 1.0);
        c.truncate() / c.w
    }

    #[test]
    fn the_frustum_edges_of_an_xr_fov_reach_the_image_edges() {
        let fov = Fov {
            left: -0.9,
            right: 0.7,
            up: 0.8,
            down: -0.95,
        };
        let p = fov.projection(50.0, 20_000.0).unwrap();
        let z = 900.0;
        let at = |ax: f32, ay: f32| Vec3::new(ax.tan() * z, ay.tan() * z, -z);
        let e = 1e-4;
        assert!((ndc(p, at(fov.left, 0.0)).x + 1.0).abs() < e);
        assert!((ndc(p, at(fov.right, 0.0)).x - 1.0).abs() < e);
        assert!((ndc(p, at(0.0, fov.up)).y - 1.0).abs() < e);
        assert!((ndc(p, at(0.0, fov.down)).y + 1.0).abs() < e);
        // Depth: 0 at the near plane, 1 at the far one (wgpu's clip space).
        assert!(ndc(p, Vec3::new(0.0, 0.0, -50.0)).z.abs() < e);
        assert!((ndc(p, Vec3::new(0.0, 0.0, -20_000.0)).z - 1.0).abs() < e);
        // A symmetric field of view is glam's perspective of the same angle.
        let s = symmetric(30.0).projection(50.0, 20_000.0).unwrap();
        let g =
            glam::camera::rh::proj::directx::perspective(60f32.to_radians(), 1.0, 50.0, 20_000.0);
        assert!(s.abs_diff_eq(g, 1e-4), "{s} vs {g}");
    }

    #[test]
    fn a_degenerate_or_non_finite_fov_is_refused() {
        let ok = symmetric(45.0);
        for bad in [
            Fov {
                left: f32::NAN,
                ..ok
            },
            Fov {
                right: f32::INFINITY,
                ..ok
            },
            Fov {
                right: ok.left,
                ..ok
            },
            Fov {
                up: -0.5,
                down: 0.5,
                ..ok
            },
            Fov { up: 1.56, ..ok },
            Fov {
                left: -0.0,
                right: 0.0,
                ..ok
            },
        ] {
            assert_eq!(bad.tangents(), None, "{bad:?}");
            assert_eq!(bad.projection(50.0, 1000.0), None, "{bad:?}");
        }
    }

    #[test]
    fn the_runtimes_eyes_become_the_rigs_eyes_in_mm() {
        let eye = |x: f32| XrEye {
            position_m: [x, 0.0, 0.0],
            orientation: [0.0, 0.0, 0.0, 1.0],
            fov: symmetric(45.0),
        };
        let eyes = hmd_eyes(&[eye(-0.032), eye(0.032)], 1440, 1600, 50.0, 20_000.0).unwrap();
        assert_eq!((eyes.width, eyes.height), (1440, 1600));
        let left = eyes.eye_to_hmd[0].transform_point3(Vec3::ZERO);
        let right = eyes.eye_to_hmd[1].transform_point3(Vec3::ZERO);
        assert!(
            (left - Vec3::new(-32.0, 0.0, 0.0)).length() < 1e-3,
            "{left}"
        );
        assert!(
            (right - Vec3::new(32.0, 0.0, 0.0)).length() < 1e-3,
            "{right}"
        );
        assert!(eyes.mono_to_hmd.transform_point3(Vec3::ZERO).length() < 1e-3);
        // A NaN pose or a zero quaternion from the runtime: no eyes (the last ones are kept).
        let mut bad = eye(0.032);
        bad.position_m[1] = f32::NAN;
        assert!(hmd_eyes(&[eye(-0.032), bad], 1440, 1600, 50.0, 20_000.0).is_none());
        bad = eye(0.032);
        bad.orientation = [0.0; 4];
        assert!(hmd_eyes(&[eye(-0.032), bad], 1440, 1600, 50.0, 20_000.0).is_none());
    }

    #[test]
    fn xr_time_and_the_monotonic_clock_convert_both_ways_without_wrapping() {
        // The runtime's clock 5 s ahead of CLOCK_MONOTONIC.
        let c = XrClock::from_pair(10_000_000_000, 5_000_000_000);
        assert_eq!(c.to_monotonic(10_016_666_667), Some(5_016_666_667));
        assert_eq!(c.to_xr(5_016_666_667), Some(10_016_666_667));
        for mono in [0u64, 1, 123_456_789_012, i64::MAX as u64 - 5_000_000_000] {
            let xr = c.to_xr(mono).unwrap();
            assert_eq!(c.to_monotonic(xr), Some(mono));
        }
        // Before the monotonic zero, past i64, non-positive XrTimes: refused, never wrapped.
        assert_eq!(c.to_monotonic(4_999_999_999), None);
        assert_eq!(c.to_xr(u64::MAX), None);
        let behind = XrClock::from_pair(1_000, 5_000_000_000);
        assert_eq!(behind.to_xr(1_000_000), None);
        assert_eq!(behind.to_monotonic(i64::MIN), None);
        // timespec round trip and its malformed values.
        assert_eq!(timespec_ns(3, 250), Some(3_000_000_250));
        assert_eq!(ns_timespec(3_000_000_250), (3, 250));
        assert_eq!(timespec_ns(-1, 0), None);
        assert_eq!(timespec_ns(0, 1_000_000_000), None);
        assert_eq!(timespec_ns(0, -1), None);
        assert_eq!(timespec_ns(i64::MAX, 0), None);
    }

    #[test]
    fn the_vulkan_version_is_the_loaders_capped_at_1_3_and_at_least_1_1() {
        let v = |major, minor, patch| vk_api_version(major, minor) | patch;
        assert_eq!(vulkan_instance_version(v(1, 3, 239)), Some(v(1, 3, 0)));
        assert_eq!(vulkan_instance_version(v(1, 4, 0)), Some(v(1, 3, 0)));
        assert_eq!(vulkan_instance_version(v(1, 2, 131)), Some(v(1, 2, 131)));
        assert_eq!(vulkan_instance_version(v(1, 1, 0)), Some(v(1, 1, 0)));
        assert_eq!(vulkan_instance_version(v(1, 0, 65)), None);
        assert_eq!(vulkan_instance_version(0), None);
        // The variant bits (29..31) are not part of the version.
        assert_eq!(
            vulkan_instance_version((7 << 29) | v(1, 2, 0)),
            Some(v(1, 2, 0))
        );
    }

    #[test]
    fn the_runs_xr_figures_count_frames_and_spread_the_intervals() {
        let mut s = XrStats::default();
        assert_eq!(s.lead_at_wait.ms(), None);
        assert!(s.to_string().contains("at xrWaitFrame none"), "{s}");
        // Display times 50 ms apart; waits return 60 ms before; one submit comes 5 ms late.
        s.waited(1_060_000_000, 1_000_000_000);
        s.ended(Some(1_060_000_000), 1_030_000_000, true);
        s.waited(1_110_000_000, 1_050_000_000);
        s.ended(Some(1_110_000_000), 1_115_000_000, true);
        s.waited(1_160_000_000, 1_100_000_000);
        s.ended(None, 1_120_000_000, false);
        assert_eq!((s.waited, s.layers, s.empty), (3, 2, 1));
        assert_eq!(s.lead_at_wait.ms(), Some((60.0, 60.0, 60.0)));
        assert_eq!(s.lead_at_submit.ms(), Some((-5.0, 12.5, 30.0)));
        assert_eq!(s.period.count(), 2);
        assert_eq!(s.period.ms(), Some((50.0, 50.0, 50.0)));
        let line = s.to_string();
        assert!(
            line.contains("2 ended with both eyes' projection layer"),
            "{line}"
        );
        // Extremes saturate, never wrap.
        let mut e = Spread::default();
        e.add(signed_diff(u64::MAX, 0));
        e.add(signed_diff(0, u64::MAX));
        assert_eq!((e.min, e.max), (i64::MIN, i64::MAX));
    }

    #[test]
    fn an_additive_display_gets_the_see_through_look_others_the_scenes() {
        for look in Look::ALL {
            assert_eq!(look_for_blend(BlendMode::Additive, look), Look::SeeThrough);
            assert_eq!(look_for_blend(BlendMode::Opaque, look), look);
            assert_eq!(look_for_blend(BlendMode::AlphaBlend, look), look);
        }
    }

    #[test]
    fn additive_is_chosen_whenever_the_runtime_offers_it() {
        use BlendMode::*;
        assert_eq!(choose_blend_mode(&[Opaque, Additive]), Some(Additive));
        assert_eq!(choose_blend_mode(&[Additive]), Some(Additive));
        assert_eq!(choose_blend_mode(&[AlphaBlend, Opaque]), Some(Opaque));
        assert_eq!(choose_blend_mode(&[AlphaBlend]), Some(AlphaBlend));
        assert_eq!(choose_blend_mode(&[]), None);
    }

    #[test]
    fn the_swapchain_format_is_ours_when_offered_else_the_runtimes_first_srgb() {
        use vk_format::*;
        use wgpu::TextureFormat as F;
        assert_eq!(
            choose_swapchain_format(&[B8G8R8A8_SRGB, R8G8B8A8_SRGB]),
            Some((R8G8B8A8_SRGB, F::Rgba8UnormSrgb))
        );
        assert_eq!(
            choose_swapchain_format(&[97, B8G8R8A8_UNORM, B8G8R8A8_SRGB]),
            Some((B8G8R8A8_SRGB, F::Bgra8UnormSrgb))
        );
        assert_eq!(
            choose_swapchain_format(&[97, R8G8B8A8_UNORM]),
            Some((R8G8B8A8_UNORM, F::Rgba8Unorm))
        );
        // Only float/HDR formats (e.g. VK_FORMAT_R16G16B16A16_SFLOAT = 97): none we fill.
        assert_eq!(choose_swapchain_format(&[97, 64]), None);
        assert_eq!(choose_swapchain_format(&[]), None);
    }
}
