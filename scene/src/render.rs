//! The `[render]` table: how the renderer draws the lungs (mode, look, colour, anti-aliasing, level
//! of detail, the eyes' images and the rig's calibration and optics files).

use serde::{Deserialize, Serialize};

use crate::TableError;

/// How lungs are drawn.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DrawMode {
    /// Shaded triangles.
    Triangles,
    /// Point splats (one camera-facing quad per vertex).
    Points,
}

/// How the lungs' surface is shown over the patient (`[render] look`, `lungdyn demo --look`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum Look {
    /// Lit tissue, opaque: the lungs hide what is behind them; a tumour is drawn through them.
    #[default]
    Opaque,
    /// Lit tissue, translucent with a fresnel rim (both lungs blended order-independently, weighted
    /// blended OIT): the far wall, the other lung and an opaque tumour show through.
    Translucent,
    /// For an optical see-through (additive) display, where black is transparent: the lungs emit
    /// light, mostly at their silhouettes, and add to the view of the patient instead of covering it.
    SeeThrough,
}

impl Look {
    /// Every look, in the order `--help` lists them.
    pub const ALL: [Look; 3] = [Look::Opaque, Look::Translucent, Look::SeeThrough];

    /// The name in scene files and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Look::Opaque => "opaque",
            Look::Translucent => "translucent",
            Look::SeeThrough => "see-through",
        }
    }
}

/// What the lungs' colour shows (`[render] color`, `lungdyn demo --color`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum ColorMode {
    /// The tissue's own colour (pink, the right lung a little warmer than the left).
    #[default]
    Tissue,
    /// Displacement from the rest (FRC) position, mm: dark blue 0 → yellow 20 mm and over.
    Displacement,
    /// Local expansion relative to FRC, a proxy of regional ventilation (the surface's areal strain
    /// around each vertex, `(A/A₀)^(3/2) − 1`): blue −10 % (collapsing), white 0, red +30 %.
    Ventilation,
    /// Each lobe its own colour (`lung_model::mesh::lobes::Lobe::colour`) from the kernel's per-vertex
    /// lobe codes, with the fissures drawn as dark lines where lobes meet; a lung whose kernel has
    /// no lobe section is drawn grey and the renderer says so (start line and HUD legend).
    Lobes,
}

impl ColorMode {
    /// Every colour mode, in the order `--help` lists them.
    pub const ALL: [ColorMode; 4] = [
        ColorMode::Tissue,
        ColorMode::Displacement,
        ColorMode::Ventilation,
        ColorMode::Lobes,
    ];

    /// The name in scene files and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            ColorMode::Tissue => "tissue",
            ColorMode::Displacement => "displacement",
            ColorMode::Ventilation => "ventilation",
            ColorMode::Lobes => "lobes",
        }
    }
}

macro_rules! named_enum_text {
    ($t:ty, $what:literal) => {
        impl std::fmt::Display for $t {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str(self.name())
            }
        }

        impl std::str::FromStr for $t {
            type Err = String;
            fn from_str(s: &str) -> Result<Self, String> {
                <$t>::ALL
                    .into_iter()
                    .find(|v| v.name() == s)
                    .ok_or_else(|| {
                        let names: Vec<&str> = <$t>::ALL.iter().map(|v| v.name()).collect();
                        format!("unknown {} {s:?} ({})", $what, names.join(", "))
                    })
            }
        }
    };
}
named_enum_text!(Look, "look");
named_enum_text!(ColorMode, "colour mode");
named_enum_text!(Governor, "governor");
named_enum_text!(GovernorStart, "governor start");

/// Whether the renderer trades drawing quality for the frame's deadline (`[render] governor`,
/// `lungdyn demo --governor`; docs/LATENCY.md "The governor").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum Governor {
    /// When frames take longer than the display period allows, draw less — in a fixed order:
    /// MSAA off, coarser draw levels, only the drawn level's vertices moved (their normals from
    /// its triangles), the translucent look made opaque — and take it back when there is time
    /// again. The deformation's accuracy (mode, bands, each drawn vertex) is not touched unless
    /// the scene opts in ([`RenderScene::governor_least_bands`]).
    #[default]
    HoldDeadline,
    /// Always draw at the scene's quality, late or not.
    Off,
}

impl Governor {
    /// Every setting, in the order `--help` lists them.
    pub const ALL: [Governor; 2] = [Governor::HoldDeadline, Governor::Off];

    /// The name in scene files and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Governor::HoldDeadline => "hold-deadline",
            Governor::Off => "off",
        }
    }
}

/// Where the governor starts a run (`[render] governor_start`, `lungdyn demo --governor-start`;
/// docs/LATENCY.md "Where a run starts").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum GovernorStart {
    /// Where the last run of the same lungs, drawing settings and frame target on the same adapter
    /// settled (kept in the cache folder when a run ends after holding one quality for 5 s), so a
    /// heavy scene does not spend its first frames late stepping down; at full quality where
    /// nothing is kept. The governor still takes steps back when there is time.
    #[default]
    Remembered,
    /// Always at the scene's full quality (what the last run learnt is neither read nor kept).
    Full,
}

impl GovernorStart {
    /// Every setting, in the order `--help` lists them.
    pub const ALL: [GovernorStart; 2] = [GovernorStart::Remembered, GovernorStart::Full];

    /// The name in scene files and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            GovernorStart::Remembered => "remembered",
            GovernorStart::Full => "full",
        }
    }

    fn is_default(&self) -> bool {
        *self == GovernorStart::default()
    }
}

/// The coarsest draw level of detail a scene may force (`[render] lod = N`): level k draws about
/// 4⁻ᵏ of the lungs' triangles; a lung whose mesh is too small for level N draws its coarsest.
pub const MAX_LOD_LEVEL: u8 = 5;

/// Which triangles the lungs are drawn with (`[render] lod`, `lungdyn demo --lod`): every physics
/// vertex is deformed either way; a coarser level draws fewer triangles over the same vertices.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Lod {
    /// Per frame from the lungs' size on screen (fewer triangles when they cover few pixels).
    #[default]
    Auto,
    /// Always every triangle (no levels are built).
    Off,
    /// Always this level (0: every triangle; up to [`MAX_LOD_LEVEL`]).
    Level(u8),
}

impl Lod {
    /// What a bad value should have been (the scene's and the command line's error).
    pub const EXPECTED: &'static str = "give \"auto\", \"off\" or a level 0..5 (0: every triangle)";
}

impl std::fmt::Display for Lod {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Lod::Auto => f.write_str("auto"),
            Lod::Off => f.write_str("off"),
            Lod::Level(n) => write!(f, "{n}"),
        }
    }
}

impl std::str::FromStr for Lod {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "auto" => Ok(Lod::Auto),
            "off" => Ok(Lod::Off),
            _ => s
                .parse::<u8>()
                .ok()
                .filter(|n| *n <= MAX_LOD_LEVEL && !s.starts_with('+'))
                .map(Lod::Level)
                .ok_or_else(|| format!("lod {s:?}: {}", Lod::EXPECTED)),
        }
    }
}

impl Serialize for Lod {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            Lod::Level(n) => s.serialize_u8(*n),
            other => s.serialize_str(&other.to_string()),
        }
    }
}

impl<'de> Deserialize<'de> for Lod {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Raw {
            Name(String),
            Level(i64),
            Other(toml::Value),
        }
        let bad =
            |what: String| D::Error::custom(format!("[render] lod = {what}: {}", Lod::EXPECTED));
        use serde::de::Error as _;
        match Raw::deserialize(d)? {
            Raw::Name(s) => s.parse().map_err(|_| bad(format!("{s:?}"))),
            Raw::Level(n) => u8::try_from(n)
                .ok()
                .filter(|n| *n <= MAX_LOD_LEVEL)
                .map(Lod::Level)
                .ok_or_else(|| bad(n.to_string())),
            Raw::Other(v) => Err(bad(v.to_string())),
        }
    }
}

/// Multisample anti-aliasing sample counts the renderer accepts (`[render] msaa`).
pub const MSAA_SAMPLES: [u32; 2] = [1, 4];

/// `[render]` table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RenderScene {
    /// Triangles or point splats.
    pub mode: DrawMode,
    /// Opaque, translucent or see-through.
    pub look: Look,
    /// What the colour shows.
    pub color: ColorMode,
    /// Samples per pixel: 4 (multisampled, resolved before read-back) or 1 (off). Unset: 4 on a
    /// GPU, 1 on a software rasterizer (lavapipe shades every sample on the CPU: 4× costs it
    /// 2.3–2.6× the frame, docs/LOOKS.md); the renderer's start line says which it drew with.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub msaa: Option<u32>,
    /// Draw level of detail: "auto" (fewer triangles when the lungs cover few pixels), "off" or a
    /// fixed level ([`Lod`]).
    pub lod: Lod,
    /// Whether drawing quality gives way to the frame's deadline ([`Governor`]).
    pub governor: Governor,
    /// The accuracy opt-in: once every drawing step is given up and frames are still late, the
    /// governor may also cap the spherical-harmonic mode's bands, one band at a time, down to this
    /// many (1..8). Unset (the default): the deformation's accuracy is never lowered. Only the "sh"
    /// mode has bands to give up; what each costs in millimetres is in docs/LATENCY.md.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub governor_least_bands: Option<u32>,
    /// Where the governor starts: where the last run settled (the default) or at full quality
    /// ([`GovernorStart`]).
    #[serde(skip_serializing_if = "GovernorStart::is_default")]
    pub governor_start: GovernorStart,
    /// Side-by-side stereo from the HMD pose.
    pub stereo: bool,
    /// Inter-pupillary distance, mm.
    pub ipd_mm: f32,
    /// Width of one eye's image, pixels.
    pub width: u32,
    /// Height of the image, pixels.
    pub height: u32,
    /// Vertical field of view, degrees.
    pub fov_y_deg: f32,
    /// Point-splat diameter, mm.
    pub splat_mm: f32,
    /// The calibration file `lungdyn register` writes (relative to the scene file): where the lungs'
    /// model frame (the meshes' body frame, mm) is relative to the patient reference tool. Without
    /// one the renderer places the lungs at a fixed offset from the reference.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub calibration: Option<std::path::PathBuf>,
    /// The HMD optics file (relative to the scene file; `lungdyn hmd check FILE` shows it): each
    /// eye's offset, orientation and frustum, and the per-eye resolution, which then replace
    /// `ipd_mm`, `fov_y_deg`, `width` and `height`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub hmd: Option<std::path::PathBuf>,
}

impl Default for RenderScene {
    fn default() -> Self {
        Self {
            mode: DrawMode::Triangles,
            look: Look::Opaque,
            color: ColorMode::Tissue,
            msaa: None,
            lod: Lod::Auto,
            governor: Governor::HoldDeadline,
            governor_least_bands: None,
            governor_start: GovernorStart::Remembered,
            stereo: false,
            ipd_mm: 63.0,
            width: 800,
            height: 600,
            fov_y_deg: 30.0,
            splat_mm: 2.5,
            calibration: None,
            hmd: None,
        }
    }
}

impl RenderScene {
    /// Range checks serde cannot express: the image size, field of view, eye separation, splat size
    /// and sample count.
    pub fn validate(&self) -> Result<(), TableError> {
        let r = self;
        if !(16..=8192).contains(&r.width) || !(16..=8192).contains(&r.height) {
            return Err(TableError::ImageSize {
                width: r.width,
                height: r.height,
            });
        }
        if !(r.fov_y_deg > 1.0 && r.fov_y_deg < 170.0) {
            return Err(TableError::FieldOfView(r.fov_y_deg));
        }
        if !(r.ipd_mm >= 0.0 && r.ipd_mm < 200.0) || !(r.splat_mm > 0.0 && r.splat_mm < 100.0) {
            return Err(TableError::EyeOrSplat {
                ipd_mm: r.ipd_mm,
                splat_mm: r.splat_mm,
            });
        }
        if let Some(n) = r.msaa.filter(|n| !MSAA_SAMPLES.contains(n)) {
            return Err(TableError::Msaa(n));
        }
        if let Some(n) = r.governor_least_bands.filter(|n| !(1..=8).contains(n)) {
            return Err(TableError::LeastBands(n));
        }
        Ok(())
    }
}
