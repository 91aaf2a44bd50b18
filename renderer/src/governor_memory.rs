//! Where the quality governor starts a run (`[render] governor_start`, "remembered" by default;
//! issue 36; docs/LATENCY.md "Where a run starts").
//!
//! **Why**: a heavy scene's run started at full quality and stepped down the ladder frame by frame,
//! every one of those frames late (a 100k lung on lavapipe: about 40 frames, most of a 30 s run's
//! missed deadlines). A run that ends after holding one quality for [`SETTLED_FRAMES`] keeps it —
//! with what each step it had given up bought — and the next run of the same lungs, drawing
//! settings and frame target on the same adapter starts there. It is a start, not a setting: the
//! governor still takes steps back when frames have room (predicted with the remembered gains) and
//! gives more up when they do not, and the next run keeps where that one settled.
//!
//! **Where**: the draw levels' cache folder ([`crate::lod_cache::dir_from_env`]: `$LUNGDYN_CACHE_DIR`,
//! systemd's `$CACHE_DIRECTORY`, `$XDG_CACHE_HOME/lungdyn` or `~/.cache/lungdyn`; `off`: nothing read
//! or kept), one small JSON file per setting, `governor-<key>.json`, the key an xxh3-64 of
//! [`FORMAT`], the adapter (name, backend, driver, type), the ladder's steps, the frame target, the
//! image size, the sample count, the deformation mode, the vertex count and the draw levels'
//! triangle counts: another GPU, look, size or mesh is another file, never a stale start.
//!
//! **Trust nothing read**: the file's format and key, its steps (named as this ladder names them,
//! in its order), the count given up within them and every gain finite and at least 1; anything
//! else starts at full quality and the start line says why. Written atomically
//! ([`outfile::write_atomically`]); a run at full quality with nothing kept before writes nothing.

use std::path::{Path, PathBuf};

use crate::governor::{Governor, Quality, Step};

/// The file's format; a change to what is kept or how it is keyed changes it.
pub const FORMAT: u32 = 1;
/// Frames a run must have held its last quality for at its end to keep it (5 s at 60 Hz): a run
/// that changed in its last seconds had not settled.
pub const SETTLED_FRAMES: u32 = 300;
/// Largest file read (one is a few hundred bytes; anything far larger is not one).
const MAX_BYTES: u64 = 64 * 1024;
/// Most a remembered step may have bought (a frame 1000× faster without it is not a measurement).
const MOST_GAIN: f64 = 1000.0;

/// What a run keeps for the next one.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Settled {
    /// [`FORMAT`].
    pub format: u32,
    /// The key, 16 hexadecimal digits (the file's name holds it too).
    pub key: String,
    /// The adapter, for a person reading the file.
    pub adapter: String,
    /// The governor's ladder, each step named as the start line names it.
    pub steps: Vec<String>,
    /// Steps given up where the run settled (0: full quality).
    pub given_up: usize,
    /// That quality in words.
    pub quality: String,
    /// What each step given up bought: its frames' cost before over after (≥ 1).
    pub bought: Vec<f64>,
    /// Frames the run held that quality for at its end.
    pub held_frames: u32,
    /// Frames the run drew.
    pub frames: u64,
}

/// What the start found.
#[derive(Debug, Clone, PartialEq)]
pub enum Start {
    /// Nothing kept for this setting: full quality.
    Nothing,
    /// Where the last run settled, from this file.
    Remembered {
        /// The file.
        path: PathBuf,
        /// Steps given up.
        given_up: usize,
        /// What each bought.
        bought: Vec<f64>,
    },
    /// A file was there and was not used (the reason): full quality.
    Refused {
        /// The file.
        path: PathBuf,
        /// Why.
        why: String,
    },
}

/// Where the run's memory lives, for its start and its end.
#[derive(Debug, Clone, PartialEq)]
pub struct Memory {
    /// The file.
    pub path: PathBuf,
    /// Its key.
    pub key: u64,
    /// The adapter in words.
    pub adapter: String,
}

/// The settings a start is keyed by.
#[derive(Debug, Clone, PartialEq)]
pub struct Fingerprint<'a> {
    /// The adapter in words, with its type.
    pub adapter: String,
    /// The ladder.
    pub steps: &'a [Step],
    /// The frame target, ns.
    pub target_ns: u64,
    /// The image, pixels.
    pub image: (u32, u32),
    /// Samples per pixel at full quality.
    pub samples: u32,
    /// The deformation mode, vertex count and draw levels' triangle counts.
    pub lungs: String,
}

impl Fingerprint<'_> {
    /// The key: an xxh3-64 of everything above and [`FORMAT`].
    pub fn key(&self) -> u64 {
        let steps: Vec<&str> = self.steps.iter().map(|s| s.name()).collect();
        let text = format!(
            "lungdyn governor memory {FORMAT}\n{}\n{}\n{}\n{}x{}\n{}\n{}",
            self.adapter,
            steps.join(", "),
            self.target_ns,
            self.image.0,
            self.image.1,
            self.samples,
            self.lungs
        );
        xxhash_rust::xxh3::xxh3_64(text.as_bytes())
    }

    /// The memory in `dir` for these settings.
    pub fn memory(&self, dir: &Path) -> Memory {
        let key = self.key();
        Memory {
            path: dir.join(format!("governor-{key:016x}.json")),
            key,
            adapter: self.adapter.clone(),
        }
    }
}

impl Memory {
    /// Where to start over `steps`.
    pub fn start(&self, steps: &[Step]) -> Start {
        let bytes = match std::fs::metadata(&self.path).and_then(|m| {
            if m.len() > MAX_BYTES {
                Err(std::io::Error::other(format!(
                    "{} bytes, larger than any governor memory ({MAX_BYTES} at most)",
                    m.len()
                )))
            } else {
                std::fs::read(&self.path)
            }
        }) {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Start::Nothing,
            Err(e) => {
                return Start::Refused {
                    path: self.path.clone(),
                    why: format!("unreadable: {e}"),
                }
            }
        };
        let refused = |why: String| Start::Refused {
            path: self.path.clone(),
            why,
        };
        let settled: Settled = match serde_json::from_slice(&bytes) {
            Ok(s) => s,
            Err(e) => return refused(format!("not a governor memory: {e}")),
        };
        match check(&settled, self.key, steps) {
            Ok(()) if settled.given_up == 0 => Start::Nothing,
            Ok(()) => Start::Remembered {
                path: self.path.clone(),
                given_up: settled.given_up,
                bought: settled.bought,
            },
            Err(why) => refused(why),
        }
    }

    /// Keep where `governor` settled after `frames` drawn, if it did: `existed` says whether a file
    /// was there at the start (a run at full quality keeps nothing unless one was).
    pub fn keep(&self, governor: &Governor, frames: u64, existed: bool) -> Kept {
        let held = governor.frames_since_change();
        if held < SETTLED_FRAMES {
            return Kept::NotSettled { held_frames: held };
        }
        if governor.taken() == 0 && !existed {
            return Kept::Nothing;
        }
        let settled = Settled {
            format: FORMAT,
            key: format!("{:016x}", self.key),
            adapter: self.adapter.clone(),
            steps: governor
                .steps()
                .iter()
                .map(|s| s.name().to_string())
                .collect(),
            given_up: governor.taken(),
            quality: governor.quality().describe(),
            bought: governor.bought(),
            held_frames: held,
            frames,
        };
        let text = match serde_json::to_string_pretty(&settled) {
            Ok(t) => t + "\n",
            Err(e) => {
                return Kept::Failed {
                    path: self.path.clone(),
                    why: e.to_string(),
                }
            }
        };
        let written = self
            .path
            .parent()
            .map_or(Ok(()), std::fs::create_dir_all)
            .map_err(|e| e.to_string())
            .and_then(|()| {
                outfile::write_atomically(&self.path, |w| {
                    std::io::Write::write_all(w, text.as_bytes())
                })
                .map_err(|e| e.to_string())
            });
        match written {
            Ok(()) => Kept::Written {
                path: self.path.clone(),
                quality: governor.quality(),
            },
            Err(why) => Kept::Failed {
                path: self.path.clone(),
                why,
            },
        }
    }
}

/// What the run's end kept.
#[derive(Debug, Clone, PartialEq)]
pub enum Kept {
    /// Kept: this quality, in this file.
    Written {
        /// The file.
        path: PathBuf,
        /// The quality kept.
        quality: Quality,
    },
    /// The last change came too few frames before the end.
    NotSettled {
        /// Frames held.
        held_frames: u32,
    },
    /// Full quality and nothing kept before: nothing to write.
    Nothing,
    /// Writing failed.
    Failed {
        /// The file.
        path: PathBuf,
        /// Why.
        why: String,
    },
}

impl Kept {
    /// For the renderer's closing line.
    pub fn describe(&self) -> String {
        match self {
            Kept::Written { path, quality } => format!(
                "settled at {} quality: the next run of these lungs here starts there ({})",
                quality.describe(),
                path.display()
            ),
            Kept::NotSettled { held_frames } => format!(
                "not settled (its last change {held_frames} frames before the end, fewer than \
                 {SETTLED_FRAMES}): where the next run starts is unchanged"
            ),
            Kept::Nothing => "settled at full quality: nothing to keep".to_string(),
            Kept::Failed { path, why } => {
                format!("where it settled not kept: {}: {why}", path.display())
            }
        }
    }
}

impl Start {
    /// For the start line; `None` where nothing was kept.
    pub fn describe(&self, steps: &[Step]) -> Option<String> {
        match self {
            Start::Nothing => None,
            Start::Remembered { path, given_up, .. } => Some(format!(
                "starts at {} quality, where the last run of these lungs on this adapter settled \
                 ({}; --governor-start full starts at full quality)",
                Quality::of(steps, *given_up).describe(),
                path.display()
            )),
            Start::Refused { path, why } => Some(format!(
                "starts at full quality: {} was not used: {why}",
                path.display()
            )),
        }
    }
}

/// A kept file against this start's key and ladder.
pub fn check(settled: &Settled, key: u64, steps: &[Step]) -> Result<(), String> {
    if settled.format != FORMAT {
        return Err(format!(
            "format {} where this renderer keeps {FORMAT}",
            settled.format
        ));
    }
    if settled.key != format!("{key:016x}") {
        return Err(format!(
            "its key {} is not this setting's {key:016x}",
            settled.key
        ));
    }
    let names: Vec<&str> = steps.iter().map(|s| s.name()).collect();
    if settled.steps != names {
        return Err(format!(
            "its steps ({}) are not this ladder's ({})",
            settled.steps.join(", "),
            names.join(", ")
        ));
    }
    if settled.given_up > steps.len() {
        return Err(format!(
            "{} steps given up of {}",
            settled.given_up,
            steps.len()
        ));
    }
    if settled.bought.len() != settled.given_up {
        return Err(format!(
            "{} gains for {} steps given up",
            settled.bought.len(),
            settled.given_up
        ));
    }
    if let Some(g) = settled
        .bought
        .iter()
        .find(|g| !(g.is_finite() && (1.0..=MOST_GAIN).contains(*g)))
    {
        return Err(format!("a step's gain {g} is not within 1..{MOST_GAIN}"));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: u64 = 1_000_000;

    fn ladder() -> Vec<Step> {
        vec![Step::MsaaOff, Step::CoarserLod, Step::DrawnOnly]
    }

    fn print(steps: &[Step]) -> Fingerprint<'_> {
        Fingerprint {
            adapter: "llvmpipe (Vulkan, llvmpipe Mesa) Cpu".into(),
            steps,
            target_ns: 13_700_000,
            image: (800, 600),
            samples: 4,
            lungs: "Basis, 20176 vertices, levels [40000, 10000]".into(),
        }
    }

    fn dir(tag: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!(
            "lungdyn-governor-memory-{tag}-{}",
            std::process::id()
        ));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    /// A governor settled after giving up `k` steps, each having bought `gain`, held `held` frames.
    fn settled(k: usize, held: u32) -> Governor {
        let mut g = Governor::new(ladder(), 10 * MS);
        g.start_at(k, &[2.0, 1.5, 1.25][..k]);
        for _ in 0..held {
            // 7.5 ms frames: never over the target, never predicted to fit a step back.
            let _ = g.observe(7_500_000);
        }
        g
    }

    /// Kept where it settled, read back as the same start; nothing kept before settling or at
    /// full quality with nothing there; full quality after a step back kept over the old file.
    #[test]
    fn where_a_run_settled_is_kept_and_the_next_run_starts_there() {
        let steps = ladder();
        let d = dir("round");
        let memory = print(&steps).memory(&d);
        assert_eq!(memory.start(&steps), Start::Nothing);
        assert_eq!(
            memory.keep(&settled(2, SETTLED_FRAMES - 1), 900, false),
            Kept::NotSettled {
                held_frames: SETTLED_FRAMES - 1
            }
        );
        assert_eq!(memory.keep(&settled(0, 400), 900, false), Kept::Nothing);
        assert!(!memory.path.exists(), "nothing written");
        let g = settled(2, 400);
        assert!(matches!(memory.keep(&g, 900, false), Kept::Written { .. }));
        assert_eq!(
            memory.start(&steps),
            Start::Remembered {
                path: memory.path.clone(),
                given_up: 2,
                bought: vec![2.0, 1.5],
            }
        );
        let said = memory.start(&steps).describe(&steps).unwrap();
        assert!(said.contains("MSAA off, LOD +1"), "{said}");
        // A later run back at full quality replaces it.
        assert!(matches!(
            memory.keep(&settled(0, 400), 900, true),
            Kept::Written { .. }
        ));
        assert_eq!(memory.start(&steps), Start::Nothing);
        let _ = std::fs::remove_dir_all(&d);
    }

    /// Every part of the fingerprint is part of the key.
    #[test]
    fn another_adapter_size_target_or_mesh_is_another_key() {
        let steps = ladder();
        let base = print(&steps);
        let shorter = [Step::MsaaOff];
        let others = [
            Fingerprint {
                adapter: "NVIDIA H200 (Vulkan) DiscreteGpu".into(),
                ..base.clone()
            },
            Fingerprint {
                steps: &shorter,
                ..base.clone()
            },
            Fingerprint {
                target_ns: 16_666_667,
                ..base.clone()
            },
            Fingerprint {
                image: (1920, 1080),
                ..base.clone()
            },
            Fingerprint {
                samples: 1,
                ..base.clone()
            },
            Fingerprint {
                lungs: "Sh, 20176 vertices, levels [40000, 10000]".into(),
                ..base.clone()
            },
        ];
        for o in &others {
            assert_ne!(o.key(), base.key(), "{o:?}");
        }
        assert_eq!(print(&steps).key(), base.key());
    }

    /// A file that is not this setting's, or says what cannot be, starts at full quality and
    /// says why; an unreadable one too.
    #[test]
    fn a_kept_file_that_does_not_fit_is_refused_naming_why() {
        let steps = ladder();
        let d = dir("refused");
        let memory = print(&steps).memory(&d);
        assert!(matches!(
            memory.keep(&settled(2, 400), 900, false),
            Kept::Written { .. }
        ));
        let good: Settled = serde_json::from_slice(&std::fs::read(&memory.path).unwrap()).unwrap();
        let cases: Vec<(Settled, &str)> = vec![
            (
                Settled {
                    format: 2,
                    ..good.clone()
                },
                "format 2",
            ),
            (
                Settled {
                    key: "0123".into(),
                    ..good.clone()
                },
                "key",
            ),
            (
                Settled {
                    steps: vec!["MSAA off".into()],
                    ..good.clone()
                },
                "not this ladder's",
            ),
            (
                Settled {
                    given_up: 4,
                    ..good.clone()
                },
                "4 steps given up of 3",
            ),
            (
                Settled {
                    given_up: 1,
                    ..good.clone()
                },
                "2 gains for 1 steps",
            ),
            (
                Settled {
                    bought: vec![2.0, 0.5],
                    ..good.clone()
                },
                "gain 0.5",
            ),
            (
                Settled {
                    bought: vec![2.0, 1e9],
                    ..good.clone()
                },
                "not within",
            ),
        ];
        for (bad, needle) in cases {
            std::fs::write(&memory.path, serde_json::to_string(&bad).unwrap()).unwrap();
            match memory.start(&steps) {
                Start::Refused { why, .. } => assert!(why.contains(needle), "{needle}: {why}"),
                other => panic!("{needle}: {other:?}"),
            }
        }
        for junk in ["", "{", "[1, 2]", "{\"format\": 1}"] {
            std::fs::write(&memory.path, junk).unwrap();
            assert!(
                matches!(memory.start(&steps), Start::Refused { ref why, .. } if why.contains("not a governor memory")),
                "{junk:?}"
            );
        }
        // NaN cannot be written in JSON; a gain written as null is refused by the reader.
        let text = serde_json::to_string(&good).unwrap().replace("2.0", "null");
        std::fs::write(&memory.path, text).unwrap();
        assert!(matches!(memory.start(&steps), Start::Refused { .. }));
        // A huge file is not read.
        std::fs::write(&memory.path, vec![b' '; 100_000]).unwrap();
        assert!(
            matches!(memory.start(&steps), Start::Refused { ref why, .. } if why.contains("100000 bytes")),
            "{:?}",
            memory.start(&steps)
        );
        // A folder where the file should be.
        std::fs::remove_file(&memory.path).unwrap();
        std::fs::create_dir_all(&memory.path).unwrap();
        assert!(
            matches!(memory.start(&steps), Start::Refused { ref why, .. } if why.contains("unreadable")),
            "{:?}",
            memory.start(&steps)
        );
        assert!(matches!(
            memory.keep(&settled(2, 400), 900, true),
            Kept::Failed { .. }
        ));
        let _ = std::fs::remove_dir_all(&d);
    }
}
