//! One lungdyn run: its name, its stream names and the files its transport leaves on disk.
//!
//! Every process of a run uses the same instance name; stream names (`lungdyn/<instance>/engine`)
//! and iceoryx2's file prefix (`lungdyn_<instance>_`) derive from it, so two runs never meet and the
//! files of one run can be found and removed without touching another's.

use std::path::PathBuf;

use crate::port::PortError;

/// The streams of one lungdyn instance.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Instance {
    name: String,
}

impl Instance {
    /// Instance `name`: 1–48 characters of `[A-Za-z0-9_-]`.
    pub fn new(name: &str) -> Result<Self, PortError> {
        let ok = !name.is_empty()
            && name.len() <= 48
            && name
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_');
        if !ok {
            return Err(PortError::BadInstanceName {
                name: name.to_string(),
            });
        }
        Ok(Self {
            name: name.to_string(),
        })
    }

    /// The instance name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Stream of [`ipc_types::TrackerFrame`]s.
    pub fn tracker(&self) -> String {
        format!("lungdyn/{}/tracker", self.name)
    }
    /// Event signalled after each tracker frame.
    pub fn tracker_event(&self) -> String {
        format!("lungdyn/{}/tracker-ready", self.name)
    }
    /// Stream of [`ipc_types::EngineFrame`]s.
    pub fn engine(&self) -> String {
        format!("lungdyn/{}/engine", self.name)
    }
    /// Event signalled after each engine frame.
    pub fn engine_event(&self) -> String {
        format!("lungdyn/{}/engine-ready", self.name)
    }
    /// Stream of [`ipc_types::FrameReport`]s.
    pub fn report(&self) -> String {
        format!("lungdyn/{}/report", self.name)
    }
    /// Event signalled after each frame report.
    pub fn report_event(&self) -> String {
        format!("lungdyn/{}/report-ready", self.name)
    }

    /// The transport's file prefix for this instance: every shared-memory segment and file the
    /// instance creates starts with it.
    pub fn file_prefix(&self) -> String {
        format!("lungdyn_{}_", self.name)
    }

    /// Files of this instance still present in shared memory (`/dev/shm`) or under iceoryx2's root
    /// folder. Empty after a clean shutdown (but for iceoryx2's per-prefix node counter, which
    /// outlives the nodes by design until [`Self::remove_leftovers`]).
    pub fn leftovers(&self) -> Vec<PathBuf> {
        let prefix = self.file_prefix();
        let mut found = Vec::new();
        let mut stack = vec![PathBuf::from("/dev/shm"), crate::iox::root_path()];
        while let Some(dir) = stack.pop() {
            let Ok(entries) = std::fs::read_dir(&dir) else {
                continue;
            };
            for entry in entries.flatten() {
                let path = entry.path();
                if entry.file_type().map(|t| t.is_dir()).unwrap_or(false)
                    && !dir.starts_with("/dev/shm")
                {
                    stack.push(path.clone());
                }
                if entry.file_name().to_string_lossy().starts_with(&prefix) {
                    found.push(path);
                }
            }
        }
        found.sort();
        found
    }

    /// Delete the files [`Self::leftovers`] finds, and folders left empty by that. Only for after
    /// every process of the instance has exited: the prefix is unique to the instance, so no other
    /// run is touched. Says which files were expected (iceoryx2's per-prefix node counter, which
    /// outlives its nodes by design) and which were left behind by a process that did not clean up.
    pub fn remove_leftovers(&self) -> Cleanup {
        let mut cleanup = Cleanup::default();
        for path in self.leftovers() {
            // iceoryx2 0.10 names it `<prefix><hash>_node.<version>.global_mgmt`.
            let is_counter = path
                .file_name()
                .is_some_and(|n| n.to_string_lossy().ends_with(".global_mgmt"));
            if std::fs::remove_file(&path).is_ok() {
                if is_counter {
                    cleanup.node_counter = true;
                } else {
                    cleanup.unexpected.push(path.clone());
                }
                if let Some(dir) = path.parent() {
                    // Only succeeds when the folder is now empty.
                    let _ = std::fs::remove_dir(dir);
                }
            }
        }
        cleanup
    }
}

/// What [`Instance::remove_leftovers`] removed.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Cleanup {
    /// iceoryx2's node-counter segment of the instance was removed (expected after every run).
    pub node_counter: bool,
    /// Other files of the instance that were still there (a process did not clean up).
    pub unexpected: Vec<PathBuf>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn instance_names_are_validated() {
        assert!(Instance::new("demo-1_a").is_ok());
        for bad in ["", "a/b", "a b", "ü"] {
            assert!(
                matches!(Instance::new(bad), Err(PortError::BadInstanceName { .. })),
                "{bad:?}"
            );
        }
        assert!(Instance::new(&"x".repeat(48)).is_ok());
        assert!(Instance::new(&"x".repeat(49)).is_err());
    }

    #[test]
    fn streams_and_files_carry_the_instance_name() {
        let i = Instance::new("abc").unwrap();
        assert_eq!(i.engine(), "lungdyn/abc/engine");
        assert_eq!(i.file_prefix(), "lungdyn_abc_");
    }
}
