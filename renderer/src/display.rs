//! How the frames are shown, as the command line asks: headless, a window, a display filled, or an
//! OpenXR runtime, and how to present. Options only (the renderer's, and the demo's, which passes
//! them on); [`crate::window`] and [`crate::xr_runtime`] act on them.

/// How the frames are shown: the renderer's window options, also the demo's (which passes them on).
#[derive(Debug, Clone, clap::Args)]
#[command(group(clap::ArgGroup::new("shown").args(["window", "fullscreen"]).multiple(true)))]
pub struct DisplayArgs {
    /// Show the frames in a window (needs a display, e.g. DISPLAY on X11); headless otherwise.
    #[arg(long)]
    pub window: bool,
    /// Draw both eyes into an OpenXR runtime's swapchain (a build with the `openxr` feature; the
    /// runtime paces the frames and predicts the display time). Fails naming what to install when
    /// there is no OpenXR loader or runtime.
    #[arg(long, conflicts_with_all = ["window", "fullscreen"])]
    pub xr: bool,
    /// Fill a whole display with the frames (a borderless fullscreen window; implies --window): in
    /// stereo each eye is drawn at half the display's width and its full height.
    #[arg(long)]
    pub fullscreen: bool,
    /// With --fullscreen: the display to fill, by its name (e.g. DP-1, as `xrandr` and `lungdyn
    /// doctor` show it) or its index in `lungdyn doctor`'s list; the primary display by default.
    #[arg(long, value_name = "NAME|INDEX", requires = "fullscreen")]
    pub display: Option<DisplaySel>,
    /// With a window: wait for the display's vertical blank when presenting (FIFO: adds up to a
    /// refresh period of latency; off by default, frames are paced by the engine). Same as
    /// `--present-mode fifo`.
    #[arg(long, requires = "shown", conflicts_with = "present_mode")]
    pub vsync: bool,
    /// With a window: how frames reach the display. `latency` (default) takes mailbox where the
    /// surface offers it, else immediate, else FIFO; a named mode the surface lacks is refused.
    #[arg(
        long,
        value_enum,
        default_value_t,
        requires = "shown",
        value_name = "MODE"
    )]
    pub present_mode: PresentChoice,
    /// With a window: frames the surface may queue ahead of the display
    /// (`desired_maximum_frame_latency`, 1 to 3): 1 for the least latency.
    #[arg(long, default_value_t = 1, requires = "shown", value_name = "N",
          value_parser = clap::value_parser!(u32).range(1..=3))]
    pub frame_latency: u32,
}

impl DisplayArgs {
    /// Whether frames go to a window (`--window` or `--fullscreen`).
    pub fn shown(&self) -> bool {
        self.window || self.fullscreen
    }

    /// The same options as command-line arguments (what the demo passes to the renderer).
    pub fn to_args(&self) -> Vec<String> {
        let mut out = Vec::new();
        if self.window {
            out.push("--window".to_string());
        }
        if self.fullscreen {
            out.push("--fullscreen".to_string());
        }
        if self.xr {
            out.push("--xr".to_string());
        }
        if let Some(d) = &self.display {
            out.push(format!("--display={d}"));
        }
        if self.shown() {
            if self.vsync {
                out.push("--vsync".to_string());
            } else {
                let mode = clap::ValueEnum::to_possible_value(&self.present_mode)
                    .map(|v| v.get_name().to_string())
                    .unwrap_or_default();
                out.push(format!("--present-mode={mode}"));
            }
            out.push(format!("--frame-latency={}", self.frame_latency));
        }
        out
    }
}

/// Which display `--display` names: its index in winit's list (`lungdyn doctor`'s order) or its
/// name (X11: the RandR output, e.g. `DP-1`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum DisplaySel {
    /// Position in the list, from 0.
    Index(usize),
    /// Output name, matched exactly.
    Name(String),
}

impl std::str::FromStr for DisplaySel {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let s = s.trim();
        if s.is_empty() {
            return Err(
                "empty: name a display (e.g. DP-1) or give its index (`lungdyn doctor` lists them)"
                    .into(),
            );
        }
        if s.bytes().all(|b| b.is_ascii_digit()) {
            return s
                .parse()
                .map(DisplaySel::Index)
                .map_err(|e| format!("{s}: {e}"));
        }
        Ok(DisplaySel::Name(s.to_string()))
    }
}

impl std::fmt::Display for DisplaySel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            DisplaySel::Index(i) => write!(f, "{i}"),
            DisplaySel::Name(n) => f.write_str(n),
        }
    }
}

/// How to present, asked on the command line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum PresentChoice {
    /// The least latency the surface offers: mailbox, else immediate, else FIFO.
    #[default]
    Latency,
    /// Mailbox (newest frame at vertical blank, no tearing).
    Mailbox,
    /// Immediate (at once, may tear).
    Immediate,
    /// FIFO (vertical blank, a queue: up to a refresh of latency per queued frame).
    Fifo,
}
