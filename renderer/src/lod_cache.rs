//! Draw levels kept on disk by content, so a large lung's start loads them instead of simplifying
//! again (a 400k lung's levels took ≈ 3.6 s at every start; issue 36 item 2).
//!
//! **Where**: `$LUNGDYN_CACHE_DIR`, else systemd's `$CACHE_DIRECTORY` (the installed renderer unit's
//! `CacheDirectory=lungdyn`), else `$XDG_CACHE_HOME/lungdyn`, else `$HOME/.cache/lungdyn`;
//! `LUNGDYN_CACHE_DIR=off` (or none of them set) builds every time.
//! **What**: one file per lung, `lod-<key>.bin`, the key an xxh3-64 of the lung's positions and
//! triangles, the coarsest level asked for and every constant the simplifier runs with
//! ([`FORMAT`] included) — a changed mesh, setting or simplifier is a new key, never a stale hit.
//! Only lungs of at least [`MIN_CACHED_TRIANGLES`] triangles are cached: a small lung simplifies in
//! milliseconds (the default 10k lungs: 0.06 s for both).
//!
//! **Trust nothing read**: the file's own checksum, its key, every index below the lung's vertex
//! count, level 0 equal to the lung's triangles and the level count within what may be built; any
//! failure rebuilds (and rewrites) the levels and says why once. Written atomically
//! ([`outfile::write_atomically`]): a killed start leaves no half file under the final name.
//!
//! Layout (little-endian): `LDLOD001`, key u64, vertex count u32, level count u32, refused level
//! u32 (`u32::MAX`: none) and its message (length u32, UTF-8), per level its triangle count u32 and
//! triangles (3 × u32 each), then an xxh3-64 of everything before it.

use std::path::{Path, PathBuf};

use xxhash_rust::xxh3::Xxh3;

use crate::lod::{self, LungLevels};

/// The file's magic and format; a new simplifier or layout changes it.
pub const FORMAT: &[u8; 8] = b"LDLOD001";
/// Lungs with fewer triangles are simplified at every start (milliseconds), never cached.
pub const MIN_CACHED_TRIANGLES: usize = 100_000;
/// The environment variable naming the cache folder (`off`: no cache).
pub const ENV_DIR: &str = "LUNGDYN_CACHE_DIR";

/// How a lung's levels were had.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Source {
    /// Built here; too small to cache, or no cache folder.
    Built,
    /// Read from this file.
    Loaded(PathBuf),
    /// Built here and written to this file (none was there, or it was refused: the reason).
    Cached(PathBuf, Option<String>),
    /// Built here; writing the file failed (the reason).
    NotWritten(PathBuf, String),
}

impl Source {
    /// For the renderer's start line: where the `side` lung's levels came from or went; `None`
    /// when they were simply built.
    pub fn describe(&self, side: &str) -> Option<String> {
        match self {
            Source::Built => None,
            Source::Loaded(p) => Some(format!(
                "the {side} lung's levels read from {}",
                p.display()
            )),
            Source::Cached(p, why) => Some(format!(
                "the {side} lung's levels built and kept in {}{}",
                p.display(),
                why.as_ref().map_or(String::new(), |w| format!(
                    " (the file there was refused: {w})"
                ))
            )),
            Source::NotWritten(p, e) => Some(format!(
                "the {side} lung's levels built, not kept: {}: {e}",
                p.display()
            )),
        }
    }
}

/// The cache folder from the environment ([`ENV_DIR`], XDG, home), if any.
pub fn dir_from_env() -> Option<PathBuf> {
    let var = |k: &str| std::env::var_os(k).filter(|v| !v.is_empty());
    match var(ENV_DIR) {
        Some(v) if v == "off" => None,
        Some(v) => Some(PathBuf::from(v)),
        None => var("CACHE_DIRECTORY")
            .and_then(|v| {
                let first = v.to_string_lossy().split(':').next()?.to_string();
                (!first.is_empty()).then(|| PathBuf::from(first))
            })
            .or_else(|| var("XDG_CACHE_HOME").map(|x| PathBuf::from(x).join("lungdyn")))
            .or_else(|| var("HOME").map(|h| PathBuf::from(h).join(".cache").join("lungdyn"))),
    }
}

/// The levels of one lung ([`lod::lung_levels`]) through the cache in `dir`.
pub fn lung_levels(
    positions: &[[f32; 3]],
    triangles: &[[u32; 3]],
    coarsest: u8,
    dir: Option<&Path>,
) -> (LungLevels, Source) {
    let dir = match dir {
        Some(d) if triangles.len() >= MIN_CACHED_TRIANGLES && coarsest > 0 => d,
        _ => {
            return (
                lod::lung_levels(positions, triangles, coarsest),
                Source::Built,
            )
        }
    };
    let key = key(positions, triangles, coarsest);
    let path = dir.join(format!("lod-{key:016x}.bin"));
    let refused = match std::fs::read(&path) {
        Ok(bytes) => match decode(&bytes, key, positions.len(), triangles, coarsest) {
            Ok(levels) => return (levels, Source::Loaded(path)),
            Err(why) => Some(why),
        },
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
        Err(e) => Some(format!("unreadable: {e}")),
    };
    let levels = lod::lung_levels(positions, triangles, coarsest);
    let bytes = encode(&levels, key, positions.len());
    let written = std::fs::create_dir_all(dir)
        .map_err(|e| e.to_string())
        .and_then(|_| {
            outfile::write_atomically(&path, |w| w.write_all(&bytes)).map_err(|e| e.to_string())
        });
    let source = match written {
        Ok(()) => Source::Cached(path, refused),
        Err(e) => Source::NotWritten(path, e),
    };
    (levels, source)
}

use std::io::Write as _;

/// The content key: the lung, the coarsest level and the simplifier's constants.
fn key(positions: &[[f32; 3]], triangles: &[[u32; 3]], coarsest: u8) -> u64 {
    let mut h = Xxh3::new();
    h.update(FORMAT);
    h.update(&[coarsest]);
    for c in [
        lod::LEVEL_RATIO,
        lod::ERROR_RELATIVE,
        lod::ERROR_GROWTH,
        lod::MIN_TRIANGLES as f32,
    ] {
        h.update(&c.to_le_bytes());
    }
    h.update(&(positions.len() as u64).to_le_bytes());
    h.update(bytemuck::cast_slice(positions));
    h.update(&(triangles.len() as u64).to_le_bytes());
    h.update(bytemuck::cast_slice(triangles));
    h.digest()
}

fn encode(levels: &LungLevels, key: u64, vertices: usize) -> Vec<u8> {
    let mut b = Vec::new();
    b.extend_from_slice(FORMAT);
    b.extend_from_slice(&key.to_le_bytes());
    b.extend_from_slice(&(vertices as u32).to_le_bytes());
    b.extend_from_slice(&(levels.levels.len() as u32).to_le_bytes());
    let (at, why) = levels
        .refused
        .as_ref()
        .map_or((u32::MAX, ""), |(k, w)| (*k as u32, w.as_str()));
    b.extend_from_slice(&at.to_le_bytes());
    b.extend_from_slice(&(why.len() as u32).to_le_bytes());
    b.extend_from_slice(why.as_bytes());
    for level in &levels.levels {
        b.extend_from_slice(&(level.len() as u32).to_le_bytes());
        b.extend_from_slice(bytemuck::cast_slice(level));
    }
    let sum = xxhash_rust::xxh3::xxh3_64(&b);
    b.extend_from_slice(&sum.to_le_bytes());
    b
}

/// A file's levels, or why they cannot be trusted.
fn decode(
    bytes: &[u8],
    key: u64,
    vertices: usize,
    triangles: &[[u32; 3]],
    coarsest: u8,
) -> Result<LungLevels, String> {
    let body_len = bytes
        .len()
        .checked_sub(8)
        .ok_or("shorter than its checksum")?;
    let (body, sum) = bytes.split_at(body_len);
    if xxhash_rust::xxh3::xxh3_64(body).to_le_bytes() != sum {
        return Err("its checksum does not match (a damaged or partly written file)".into());
    }
    let mut r = Reader { b: body, at: 0 };
    if r.take(8)? != FORMAT {
        return Err("not a draw-level file of this version".into());
    }
    if r.u64()? != key {
        return Err("its key is another lung's".into());
    }
    if r.u32()? as usize != vertices {
        return Err("its vertex count is another lung's".into());
    }
    let count = r.u32()? as usize;
    if count == 0 || count > coarsest as usize + 1 {
        return Err(format!(
            "{count} levels, where 1..={} may be built",
            coarsest as usize + 1
        ));
    }
    let at = r.u32()?;
    let why_len = r.u32()? as usize;
    let why = std::str::from_utf8(r.take(why_len)?)
        .map_err(|_| "its refusal message is not UTF-8")?
        .to_string();
    let refused = (at != u32::MAX).then_some((at as usize, why));
    let mut levels = Vec::with_capacity(count);
    for k in 0..count {
        let n = r.u32()? as usize;
        let raw = r.take(n.checked_mul(12).ok_or("a level's size overflows")?)?;
        let level: Vec<[u32; 3]> = raw
            .chunks_exact(12)
            .map(|t| {
                let i = |j: usize| u32::from_le_bytes(t[j..j + 4].try_into().unwrap());
                [i(0), i(4), i(8)]
            })
            .collect();
        if level.iter().flatten().any(|&i| i as usize >= vertices) {
            return Err(format!(
                "level {k} names a vertex past the lung's {vertices}"
            ));
        }
        if k == 0 && level != triangles {
            return Err("its level 0 is not the lung's triangles".into());
        }
        levels.push(level);
    }
    if r.at != body.len() {
        return Err("bytes after its last level".into());
    }
    Ok(LungLevels { levels, refused })
}

struct Reader<'a> {
    b: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], String> {
        let end = self.at.checked_add(n).filter(|&e| e <= self.b.len());
        let end = end.ok_or("it ends early")?;
        let s = &self.b[self.at..end];
        self.at = end;
        Ok(s)
    }
    fn u32(&mut self) -> Result<u32, String> {
        Ok(u32::from_le_bytes(self.take(4)?.try_into().unwrap()))
    }
    fn u64(&mut self) -> Result<u64, String> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into().unwrap()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lung(vertices: usize) -> lung_model::mesh::TriMesh {
        lung_model::mesh::generate::lung(lung_model::mesh::Side::Right, vertices)
            .expect("built-in lung")
    }

    fn temp(name: &str) -> PathBuf {
        let d =
            std::env::temp_dir().join(format!("lungdyn-lod-cache-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    #[test]
    fn a_large_lung_is_built_once_then_loaded_the_same() {
        let m = lung(60_000);
        assert!(m.triangles.len() >= MIN_CACHED_TRIANGLES);
        let dir = temp("once");
        let (built, s1) = lung_levels(&m.positions, &m.triangles, 3, Some(&dir));
        let path = match s1 {
            Source::Cached(p, None) => p,
            other => panic!("{other:?}"),
        };
        assert!(built.levels.len() >= 2);
        let (loaded, s2) = lung_levels(&m.positions, &m.triangles, 3, Some(&dir));
        assert_eq!(s2, Source::Loaded(path.clone()));
        assert_eq!(loaded, built);
        // Another coarsest level, or a moved vertex, is another key: built, not the old file.
        let (_, s3) = lung_levels(&m.positions, &m.triangles, 2, Some(&dir));
        assert!(matches!(s3, Source::Cached(p, None) if p != path));
        let mut moved = m.positions.clone();
        moved[7][0] += 0.001;
        let (_, s4) = lung_levels(&moved, &m.triangles, 3, Some(&dir));
        assert!(matches!(s4, Source::Cached(p, None) if p != path));
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn a_damaged_or_foreign_file_is_never_trusted() {
        let m = lung(60_000);
        let dir = temp("damaged");
        let (built, s) = lung_levels(&m.positions, &m.triangles, 3, Some(&dir));
        let Source::Cached(path, None) = s else {
            panic!("{s:?}")
        };
        let good = std::fs::read(&path).unwrap();
        let key = key(&m.positions, &m.triangles, 3);
        let n = m.positions.len();
        // Every truncation, a flipped byte anywhere, a file of another lung: refused with a reason.
        for cut in [0, 7, 8, 20, good.len() / 2, good.len() - 1] {
            assert!(
                decode(&good[..cut], key, n, &m.triangles, 3).is_err(),
                "cut {cut}"
            );
        }
        for at in [0, 9, 30, good.len() / 3, good.len() - 9, good.len() - 1] {
            let mut bad = good.clone();
            bad[at] ^= 0x40;
            let e = decode(&bad, key, n, &m.triangles, 3).unwrap_err();
            assert!(e.contains("checksum") || e.contains("version"), "{at}: {e}");
        }
        assert!(decode(&good, key ^ 1, n, &m.triangles, 3)
            .unwrap_err()
            .contains("another lung"));
        // A well-formed file whose indices run past the lung (checksum recomputed): refused.
        let mut past = built.clone();
        past.levels[1][0][0] = n as u32;
        let bytes = encode(&past, key, n);
        let e = decode(&bytes, key, n, &m.triangles, 3).unwrap_err();
        assert!(e.contains("past the lung"), "{e}");
        // On disk: damaged, so rebuilt, rewritten and said why.
        let mut bad = good.clone();
        bad[40] ^= 1;
        std::fs::write(&path, &bad).unwrap();
        let (again, s) = lung_levels(&m.positions, &m.triangles, 3, Some(&dir));
        assert_eq!(again, built);
        assert!(
            matches!(s, Source::Cached(_, Some(ref why)) if why.contains("checksum")),
            "{s:?}"
        );
        assert_eq!(std::fs::read(&path).unwrap(), good);
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn small_lungs_and_no_folder_are_built_and_nothing_is_written() {
        let small = lung(2_000);
        let dir = temp("small");
        let (_, s) = lung_levels(&small.positions, &small.triangles, 3, Some(&dir));
        assert_eq!(s, Source::Built);
        assert!(!dir.exists());
        let big = lung(60_000);
        let (_, s) = lung_levels(&big.positions, &big.triangles, 3, None);
        assert_eq!(s, Source::Built);
    }

    #[test]
    fn a_cache_folder_that_cannot_be_made_builds_and_says_why() {
        // LUNGDYN_CACHE_DIR naming a file, not a folder: the levels are built, not kept, and the
        // start line says where and why; nothing is written over the file.
        let big = lung(60_000);
        let file = temp("a-file");
        std::fs::write(&file, b"not a folder").unwrap();
        let (built, s) = lung_levels(&big.positions, &big.triangles, 3, Some(&file));
        assert_eq!(built, lod::lung_levels(&big.positions, &big.triangles, 3));
        let said = s.describe("right").unwrap();
        assert!(matches!(s, Source::NotWritten(..)), "{s:?}");
        assert!(
            said.contains("not kept") && said.contains("a-file"),
            "{said}"
        );
        assert_eq!(std::fs::read(&file).unwrap(), b"not a folder");
        std::fs::remove_file(&file).ok();
    }
}
