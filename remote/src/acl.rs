//! The second wall: Zenoh's own access control on every participant of a room with keys.
//!
//! The seals ([`crate::seal`]) refuse every packet whose origin may not send it, after the packet
//! has crossed the link, been handed to a worker and had its signature checked. Zenoh's access
//! control ([ACL](https://zenoh.io/docs/manual/access-control/)) refuses the same kinds earlier, by
//! the certificate's common name of the link the packet came in on: a router no longer forwards an
//! observer's event to the source, nor a site's state to the other sites, and a flood of them costs
//! the router's ingress only. Both walls stay: the ACL knows the neighbour, not the origin (a
//! router's link carries everyone's packets), so a site's replayed or altered packets still reach
//! the seals, which count them by reason.
//!
//! The rules, by the role each certificate states (ingress only; anything else is allowed):
//! * states (`…/state`, puts and history replies): only from the source and the router, which
//!   relays them;
//! * clock answers (`…/reply/*`): only from the source and the router's time relay;
//! * events (`…/event`): only from sites and the router, which relays them;
//! * Zenoh's admin space (`@/**`): from nobody (it names the files the link reads).
//!
//! Every packet the ACL drops is counted by Zenoh (its `stats` feature) with the link's common
//! name; [`refusals`] reads them from this participant's own admin space.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use serde_json::json;
use zenoh::Wait;

use crate::keys::{Role, Room};
use crate::{zerr, Keys, Net, RemoteError};

/// The `access_control` table for `room` as this participant enforces it (JSON).
pub fn config(room: &Room) -> Result<serde_json::Value, RemoteError> {
    let keys = Keys::new(&room.room)?;
    let names = |roles: &[Role]| -> Vec<String> {
        room.members
            .iter()
            .filter(|m| roles.contains(&m.role))
            .map(|m| m.name.clone())
            .collect()
    };
    // (rule, messages, key expressions, the roles that may not send them).
    let walls: [(&str, &[&str], Vec<String>, &[Role]); 4] = [
        (
            "states-only-from-the-source",
            &["put", "reply", "declare_queryable"],
            vec![
                keys.state(),
                format!("{}/**", keys.state()),
                format!("{}/@adv/**", keys.state()),
            ],
            &[Role::Site, Role::Observer],
        ),
        (
            "clock-answers-only-from-the-source-or-relay",
            &["put", "reply"],
            vec![format!("lungdyn/{}/reply/**", room.room)],
            &[Role::Site, Role::Observer],
        ),
        (
            "events-only-from-sites",
            &["put"],
            vec![keys.event(), format!("{}/**", keys.event())],
            &[Role::Source, Role::Observer],
        ),
        (
            "no-admin-space",
            &[
                "put",
                "delete",
                "query",
                "declare_queryable",
                "declare_subscriber",
            ],
            vec!["@/**".to_string()],
            &[Role::Source, Role::Site, Role::Observer, Role::Router],
        ),
    ];
    let (mut rules, mut subjects, mut policies) = (Vec::new(), Vec::new(), Vec::new());
    for (id, messages, key_exprs, roles) in walls {
        let cns = names(roles);
        if cns.is_empty() {
            continue;
        }
        rules.push(json!({
            "id": id, "messages": messages, "flows": ["ingress"],
            "permission": "deny", "key_exprs": key_exprs,
        }));
        let subject = format!("{id}-senders");
        subjects.push(json!({ "id": subject, "cert_common_names": cns }));
        policies.push(json!({ "id": id, "rules": [id], "subjects": [subject] }));
    }
    Ok(json!({
        "enabled": true,
        "default_permission": "allow",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }))
}

/// Packets Zenoh's access control dropped on this participant's links, by the link's certificate
/// common name (the neighbour it came from), read from its own admin space's metrics; links
/// since closed included.
pub fn refusals(session: &zenoh::Session) -> Result<BTreeMap<String, u64>, RemoteError> {
    let key = format!(
        "@/{}/*/metrics?compression=false;descriptors=false;per_key=false;per_link=false;disconnected=true",
        session.zid()
    );
    let replies = session
        .get(key.as_str())
        .timeout(std::time::Duration::from_secs(2))
        .wait()
        .map_err(zerr("read this session's access-control counts"))?;
    let mut out = BTreeMap::new();
    while let Ok(r) = replies.recv() {
        if let Ok(s) = r.result() {
            parse_metrics(&String::from_utf8_lossy(&s.payload().to_bytes()), &mut out);
        }
    }
    Ok(out)
}

/// A thread that reads [`refusals`] every 2 s and says when they grew, off the caller's loop
/// (a source's relay, a site's tick loop, the router's watch).
pub struct Watch {
    stop: Arc<AtomicBool>,
}

impl Watch {
    /// Watch `session` (none when `net` has no keys or its access control is off); lines start
    /// with `who`.
    pub fn start(net: &Net, session: &zenoh::Session, who: &str) -> Option<Watch> {
        if net.auth.is_none() || !net.acl {
            return None;
        }
        let stop = Arc::new(AtomicBool::new(false));
        let (st, session, who) = (Arc::clone(&stop), session.clone(), who.to_string());
        std::thread::Builder::new()
            .name("acl-watch".into())
            .spawn(move || {
                let mut said = 0u64;
                while !st.load(Ordering::Relaxed) {
                    for _ in 0..20 {
                        if st.load(Ordering::Relaxed) {
                            return;
                        }
                        std::thread::sleep(Duration::from_millis(100));
                    }
                    let Ok(now) = refusals(&session) else {
                        continue;
                    };
                    let total: u64 = now.values().sum();
                    if total > said {
                        eprintln!(
                            "{who}: access control stopped {total} packet(s) on arrival ({}): a \
                             participant sent what its role may not",
                            words(&now)
                        );
                        said = total;
                    }
                }
            })
            .ok()?;
        Some(Watch { stop })
    }
}

impl Drop for Watch {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}

/// What a participant's closing line says of its access control: `, access control stopped
/// none` (or `observer 12, …`); empty without keys or with it off.
pub fn closing_words(net: &Net, session: &zenoh::Session) -> String {
    if net.auth.is_none() || !net.acl {
        return String::new();
    }
    match refusals(session) {
        Ok(r) => format!(", access control stopped {}", words(&r)),
        Err(e) => format!(", access control's counts unread ({e})"),
    }
}

/// Add the access-control drops in OpenMetrics `text` to `out`, by `remote_cn`: the count of
/// each per-link histogram of dropped messages (`…_per_transport_bytes_count`, one series per
/// link, message kind and priority). Declarations are left out: a participant's own declarations
/// that a rule covers (its admin space's) are dropped on every link, by design, without harm.
fn parse_metrics(text: &str, out: &mut BTreeMap<String, u64>) {
    for line in text.lines() {
        if line.starts_with('#')
            || !line.contains("reason=\"access-control\"")
            || line.contains("message=\"declare\"")
        {
            continue;
        }
        let Some((head, value)) = line.rsplit_once(' ') else {
            continue;
        };
        let Some(name) = head.split('{').next() else {
            continue;
        };
        if !(name.contains("_dropped_") && name.ends_with("_per_transport_bytes_count")) {
            continue;
        }
        let cn = label(head, "remote_cn")
            .filter(|c| !c.is_empty())
            .unwrap_or_else(|| "(no certificate)".into());
        if let Ok(v) = value.trim().parse::<f64>() {
            *out.entry(cn).or_insert(0) += v as u64;
        }
    }
}

/// The value of label `name` in `head` (`metric{a="x",b="y"}`).
fn label(head: &str, name: &str) -> Option<String> {
    let start = head.find(&format!("{name}=\""))? + name.len() + 2;
    let rest = &head[start..];
    Some(rest[..rest.find('"')?].to_string())
}

/// `refusals` in words: `observer 12, site 3`, or `none`.
pub fn words(r: &BTreeMap<String, u64>) -> String {
    if r.is_empty() {
        return "none".into();
    }
    r.iter()
        .map(|(cn, n)| format!("{cn} {n}"))
        .collect::<Vec<_>>()
        .join(", ")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn access_control_drops_are_read_by_common_name() {
        let text = "\
zenoh_rx_network_message_dropped_payload_bytes_count{local_id=\"r\",priority=\"data\",message=\"put\",reason=\"access-control\"} 9
zenoh_rx_network_message_dropped_payload_per_transport_bytes_count{priority=\"data\",message=\"put\",reason=\"access-control\",remote_zid=\"a1\",remote_cn=\"observer\"} 7
zenoh_rx_network_message_dropped_payload_per_transport_bytes_sum{priority=\"data\",message=\"put\",reason=\"access-control\",remote_zid=\"a1\",remote_cn=\"observer\"} 700.0
zenoh_rx_network_message_dropped_payload_per_transport_bytes_bucket{le=\"1024.0\",priority=\"data\",message=\"put\",reason=\"access-control\",remote_zid=\"a1\",remote_cn=\"observer\"} 7
zenoh_rx_network_message_dropped_payload_per_transport_bytes_count{priority=\"data\",message=\"reply\",reason=\"access-control\",remote_zid=\"a1\",remote_cn=\"observer\"} 2
zenoh_rx_network_message_dropped_payload_per_transport_bytes_count{priority=\"control\",message=\"declare\",reason=\"access-control\",remote_zid=\"c3\",remote_cn=\"source\"} 2
zenoh_rx_network_message_dropped_payload_per_transport_bytes_count{priority=\"data\",message=\"put\",reason=\"congestion\",remote_zid=\"b2\",remote_cn=\"site\"} 9
zenoh_rx_network_message_dropped_payload_per_transport_bytes_count{priority=\"data\",message=\"put\",reason=\"access-control\",remote_zid=\"c3\",remote_cn=\"site\"} 1
";
        let mut out = BTreeMap::new();
        parse_metrics(text, &mut out);
        assert_eq!(out.get("observer"), Some(&9));
        assert_eq!(out.get("site"), Some(&1));
        assert_eq!(words(&out), "observer 9, site 1");
        assert_eq!(words(&BTreeMap::new()), "none");
    }
}
