//! Which OpenIGTLink sender streams each tool, shared by the server (which owns the table) and
//! each connection's reader ([`super::igtl_client::pump`], which asks it per sample).

use std::time::Duration;

/// A tool's sender that has not sent it for this long gives it up to another sender.
pub const TAKEOVER_AFTER: Duration = Duration::from_millis(500);

/// Which sender streams each tool: the first to send it keeps it while it keeps sending (a second
/// sender's samples of it are refused as [`crate::sample::Reject::CompetingSender`], both named);
/// when the owner has not sent it for [`TAKEOVER_AFTER`], or has gone, the next sender takes it
/// over and that is said. Two trackers (or a tracker and a forgotten test sender) streaming
/// "Patient" from different places would otherwise interleave two poses.
#[derive(Debug, Default)]
pub struct ToolOwners {
    map: std::sync::Mutex<std::collections::HashMap<String, (String, u64)>>,
}

impl ToolOwners {
    /// Whether `peer` may stream `tool` at `now_ns`: `Ok(None)` yes, `Ok(Some(note))` yes, taking
    /// it over (said), `Err(why)` no.
    pub fn claim(&self, tool: &str, peer: &str, now_ns: u64) -> Result<Option<String>, String> {
        let Ok(mut map) = self.map.lock() else {
            return Ok(None);
        };
        let key = tool.to_ascii_lowercase();
        let quiet = u64::try_from(TAKEOVER_AFTER.as_nanos()).unwrap_or(u64::MAX);
        match map.get_mut(&key) {
            None => {
                map.insert(key, (peer.to_string(), now_ns));
                Ok(None)
            }
            Some((owner, last)) if owner == peer => {
                *last = now_ns;
                Ok(None)
            }
            Some((owner, last)) if now_ns.saturating_sub(*last) >= quiet => {
                let note = format!(
                    "tool {tool:?} now from {peer} ({owner} had not sent it for {:.1} s)",
                    now_ns.saturating_sub(*last) as f64 / 1e9
                );
                *owner = peer.to_string();
                *last = now_ns;
                Ok(Some(note))
            }
            Some((owner, _)) => Err(format!(
                "{peer} sent tool {tool:?}, which {owner} is streaming: refused (the first sender \
                 keeps a tool until it is quiet for {TAKEOVER_AFTER:?}; stop one of them)"
            )),
        }
    }

    /// `peer` has gone: its tools are free at once.
    pub fn release(&self, peer: &str) {
        if let Ok(mut map) = self.map.lock() {
            map.retain(|_, (owner, _)| owner != peer);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_first_sender_keeps_a_tool_until_quiet_or_gone() {
        let o = ToolOwners::default();
        let ms = 1_000_000u64;
        assert_eq!(o.claim("Patient", "a", 0), Ok(None));
        assert_eq!(
            o.claim("patient", "a", 10 * ms),
            Ok(None),
            "names match in any case"
        );
        let e = o.claim("Patient", "b", 20 * ms).unwrap_err();
        assert!(
            e.contains("b sent tool") && e.contains("a is streaming"),
            "{e}"
        );
        assert_eq!(
            o.claim("HMD", "b", 20 * ms),
            Ok(None),
            "another tool is b's"
        );
        // a quiet for 500 ms: b takes it over, said.
        let note = o.claim("Patient", "b", 510 * ms).unwrap().unwrap();
        assert!(note.contains("now from b"), "{note}");
        assert!(o.claim("Patient", "a", 520 * ms).is_err());
        // b gone: a takes it at once.
        o.release("b");
        assert_eq!(o.claim("Patient", "a", 530 * ms), Ok(None));
    }
}
