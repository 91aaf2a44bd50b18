//! The scene's `[remote]` table: this machine's part in a shared session (seed §8.3; the
//! `lungdyn-remote` crate carries it over Zenoh).
//!
//! ```toml
//! [remote]
//! role = "source"                       # "source" (the HMD workstation), "site" or "observer"
//! room = "ward-3"                       # the shared session's name (every machine the same)
//! listen = ["tls/0.0.0.0:7447"]         # endpoints this machine listens on
//! connect = []                          # endpoints it connects to (the source, a router)
//! mode = "peer"                         # "peer", "router" or "client" (through a router)
//! lease_ms = 10000                      # a lost peer is seen within it
//! site_id = "00000000000000a1"          # optional: a fixed id (hex) instead of a fresh one
//! clock = "relay"                       # a site's clock sync: "relay" (beside the router; the
//!                                       # default in client mode) or "source" (peer's default)
//! keys = "keys/ward-3"                   # the room's keys (`lungdyn remote keys`), relative to
//!                                       # this file: mutual TLS on tls/ endpoints, sealed packets
//! identity = "source"                   # this machine's certificate in keys (default: the role)
//! insecure_lab_network = false          # without keys, allow plain TCP beyond this machine
//! ```
//!
//! Without `keys` the session is plain TCP: unencrypted and open to anyone who reaches the port.
//! It then stays on this machine (a source listens on `tcp/127.0.0.1:7447` by default) unless
//! `insecure_lab_network = true` (`--insecure-lab-network`) says the network is a closed lab's;
//! said at start-up and by `lungdyn doctor`.
//!
//! Through a router a site syncs its clock with the time relay `lungdyn remote router` runs beside
//! the router (it alone probes the source), so the source's cost does not grow with the sites;
//! peer to peer, or with `clock = "source"` behind a stock Zenoh router, each site probes the
//! source.
//!
//! `lungdyn demo` on a scene whose role is `source` starts `lungdyn remote serve` beside its
//! engine (supervised like the other processes); `lungdyn remote serve|join --scene S` take their
//! settings from the table (flags given on the command line win).

use serde::{Deserialize, Serialize};

/// A machine's part in a shared session.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RemoteRole {
    /// The engine here is the source every site follows.
    Source,
    /// A site: its own engine driven by the source's states; may send events.
    Site,
    /// A site that only watches (sends no events).
    Observer,
}

/// How the Zenoh session is reached.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ZenohMode {
    /// Peer to peer.
    Peer,
    /// A router others connect to (a classroom's hub).
    Router,
    /// A client of a router.
    Client,
}

impl ZenohMode {
    /// Zenoh's name of the mode.
    pub fn name(self) -> &'static str {
        match self {
            ZenohMode::Peer => "peer",
            ZenohMode::Router => "router",
            ZenohMode::Client => "client",
        }
    }
}

/// Whom a site probes to learn the source's clock.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ClockSync {
    /// The source itself (peer to peer; its cost grows with every site).
    Source,
    /// The time relay beside the router (`lungdyn remote router`): it answers in the source's time.
    Relay,
}

impl ClockSync {
    /// The key's value.
    pub fn name(self) -> &'static str {
        match self {
            ClockSync::Source => "source",
            ClockSync::Relay => "relay",
        }
    }
}

/// The default listen endpoint of a source without the room's keys: plain TCP on this machine
/// only (beyond it plain TCP needs [`RemoteScene::insecure_lab_network`]).
pub const DEFAULT_LISTEN: &str = "tcp/127.0.0.1:7447";
/// The default listen endpoint with the room's keys: every address, mutual TLS.
pub const DEFAULT_LISTEN_TLS: &str = "tls/0.0.0.0:7447";
/// The default link lease, ms.
pub const DEFAULT_LEASE_MS: u64 = 10_000;
/// The shortest lease accepted, ms (below it a busy machine's keep-alives miss it).
pub const MIN_LEASE_MS: u64 = 100;
/// The longest lease accepted, ms.
pub const MAX_LEASE_MS: u64 = 600_000;

/// `[remote]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RemoteScene {
    /// This machine's part.
    pub role: RemoteRole,
    /// The shared session's name.
    #[serde(default = "default_room")]
    pub room: String,
    /// Endpoints to listen on (default: a source listens on [`DEFAULT_LISTEN`], a site on none).
    #[serde(default)]
    pub listen: Option<Vec<String>>,
    /// Endpoints to connect to.
    #[serde(default)]
    pub connect: Vec<String>,
    /// Peer, router or client.
    #[serde(default = "default_mode")]
    pub mode: ZenohMode,
    /// Link lease, ms.
    #[serde(default = "default_lease")]
    pub lease_ms: u64,
    /// A fixed site id (1–16 hex digits); absent: a fresh one per run.
    #[serde(default)]
    pub site_id: Option<String>,
    /// A site's clock sync (absent: [`ClockSync::Relay`] in client mode, else
    /// [`ClockSync::Source`]); see [`Self::clock`].
    #[serde(default)]
    pub clock: Option<ClockSync>,
    /// The room's keys folder (`lungdyn remote keys`), relative to the scene file; absent: plain
    /// TCP (a closed lab network only).
    #[serde(default)]
    pub keys: Option<String>,
    /// This machine's certificate in `keys` (absent: the role's name, `source`, `site` or
    /// `observer`).
    #[serde(default)]
    pub identity: Option<String>,
    /// Without keys, allow plain TCP endpoints beyond this machine's loopback: a closed lab
    /// network's choice, never a default (see [`plain_beyond_loopback`]).
    #[serde(default)]
    pub insecure_lab_network: bool,
}

fn default_room() -> String {
    "lungdyn".into()
}
fn default_mode() -> ZenohMode {
    ZenohMode::Peer
}
fn default_lease() -> u64 {
    DEFAULT_LEASE_MS
}

/// Whether `e` is `tcp/HOST:PORT` or `tls/HOST:PORT` with a port (the transports built in).
pub fn endpoint_ok(e: &str) -> bool {
    let Some(rest) = e.strip_prefix("tcp/").or_else(|| e.strip_prefix("tls/")) else {
        return false;
    };
    let Some((host, port)) = rest.rsplit_once(':') else {
        return false;
    };
    !host.is_empty() && !host.contains(char::is_whitespace) && port.parse::<u16>().is_ok()
}

/// The first plain `tcp/` endpoint of `endpoints` whose host is not this machine's loopback
/// (`127.0.0.0/8`, `::1`, `localhost`): plain TCP there is unencrypted and open to anyone who
/// reaches it.
pub fn plain_beyond_loopback<'a>(
    endpoints: impl IntoIterator<Item = &'a String>,
) -> Option<&'a str> {
    endpoints.into_iter().map(String::as_str).find(|e| {
        let Some(rest) = e.strip_prefix("tcp/") else {
            return false;
        };
        let host = rest.rsplit_once(':').map_or(rest, |(h, _)| h);
        let host = host.trim_start_matches('[').trim_end_matches(']');
        !(host.eq_ignore_ascii_case("localhost")
            || host
                .parse::<std::net::IpAddr>()
                .is_ok_and(|ip| ip.is_loopback()))
    })
}

impl RemoteScene {
    /// The endpoints to listen on.
    pub fn listen(&self) -> Vec<String> {
        match (&self.listen, self.role) {
            (Some(l), _) => l.clone(),
            (None, RemoteRole::Source) => vec![DEFAULT_LISTEN.to_string()],
            (None, _) => Vec::new(),
        }
    }

    /// The fixed site id, if any (checked by [`Self::validate`]).
    pub fn site_id(&self) -> Option<u64> {
        self.site_id
            .as_deref()
            .and_then(|s| u64::from_str_radix(s, 16).ok())
    }

    /// Whom a site probes: the `clock` key, else the relay through a router (client mode), else
    /// the source.
    pub fn clock(&self) -> ClockSync {
        self.clock.unwrap_or(match self.mode {
            ZenohMode::Client => ClockSync::Relay,
            ZenohMode::Peer | ZenohMode::Router => ClockSync::Source,
        })
    }

    /// Check every value; the message names the key and what to write instead.
    pub fn validate(&self) -> Result<(), String> {
        if self.room.is_empty()
            || self.room.len() > 64
            || !self
                .room
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
        {
            return Err(format!(
                "room {:?}: use 1–64 letters, digits, '-' or '_' (every machine of the session \
                 the same)",
                self.room
            ));
        }
        for (key, list) in [("listen", self.listen()), ("connect", self.connect.clone())] {
            if list.len() > 16 {
                return Err(format!("{key} lists {} endpoints; at most 16", list.len()));
            }
            if let Some(bad) = list.iter().find(|e| !endpoint_ok(e)) {
                return Err(format!(
                    "{key} = {bad:?}: use tls/HOST:PORT with the room's keys, or tcp/HOST:PORT on \
                     a closed lab network (e.g. \"tls/192.168.1.10:7447\")"
                ));
            }
        }
        match (self.role, self.mode) {
            (RemoteRole::Site | RemoteRole::Observer, _) if self.connect.is_empty() => {
                return Err(format!(
                    "role = \"{}\" needs connect = [\"tcp/SOURCE_OR_ROUTER:7447\"]: a site \
                     reaches the source (or a router) there",
                    if self.role == RemoteRole::Site {
                        "site"
                    } else {
                        "observer"
                    }
                ));
            }
            (RemoteRole::Site | RemoteRole::Observer, ZenohMode::Router) => {
                return Err(
                    "mode = \"router\" is the source's (`lungdyn remote serve --mode router`: the \
                     sites connect to it) or a Zenoh router's; a site joins one with mode = \
                     \"client\" (or \"peer\") and connect = [\"tcp/ROUTER:7447\"]"
                        .into(),
                );
            }
            (_, ZenohMode::Client) if self.connect.is_empty() => {
                return Err(
                    "mode = \"client\" needs connect = [\"tcp/ROUTER:7447\"]: a client reaches \
                     everyone through a router"
                        .into(),
                );
            }
            (_, ZenohMode::Router) if self.listen().is_empty() => {
                return Err(
                    "mode = \"router\" needs listen = [\"tcp/0.0.0.0:7447\"]: the others \
                     connect to a router"
                        .into(),
                );
            }
            _ => {}
        }
        match (self.role, self.clock, self.mode) {
            (RemoteRole::Source, Some(c), _) => {
                return Err(format!(
                    "clock = \"{}\" is a site's key: the source's clock is the one every site \
                     follows (leave it out of the source's scene)",
                    c.name()
                ));
            }
            (_, Some(ClockSync::Relay), ZenohMode::Peer) => {
                return Err(
                    "clock = \"relay\" needs mode = \"client\": the time relay runs beside a \
                     Zenoh router (`lungdyn remote router`); peer to peer a site syncs with the \
                     source (clock = \"source\")"
                        .into(),
                );
            }
            _ => {}
        }
        if !(MIN_LEASE_MS..=MAX_LEASE_MS).contains(&self.lease_ms) {
            return Err(format!(
                "lease_ms = {} must be within {MIN_LEASE_MS}..{MAX_LEASE_MS} (a lost peer is seen \
                 within it; {DEFAULT_LEASE_MS} is the default)",
                self.lease_ms
            ));
        }
        if let Some(id) = &self.site_id {
            let ok = (1..=16).contains(&id.len())
                && id.chars().all(|c| c.is_ascii_hexdigit())
                && self.site_id() != Some(0);
            if !ok {
                return Err(format!(
                    "site_id = {id:?}: write 1–16 hex digits, not all zero (or leave it out for a \
                     fresh id per run)"
                ));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<RemoteScene, String> {
        let r: RemoteScene = toml::from_str(text).map_err(|e| e.to_string())?;
        r.validate().map(|_| r)
    }

    #[test]
    fn a_source_listens_by_default_and_a_site_needs_somewhere_to_connect() {
        let r = parse("role = \"source\"\n").unwrap();
        assert_eq!(r.listen(), vec![DEFAULT_LISTEN.to_string()]);
        assert_eq!(
            (r.mode, r.lease_ms, r.room.as_str()),
            (ZenohMode::Peer, 10_000, "lungdyn")
        );
        let r = parse("role = \"observer\"\nconnect = [\"tcp/10.0.0.2:7447\"]\nsite_id = \"a1\"\n")
            .unwrap();
        assert!(r.listen().is_empty());
        assert_eq!(r.site_id(), Some(0xa1));
        let e = parse("role = \"site\"\n").unwrap_err();
        assert!(e.contains("needs connect"), "{e}");
    }

    #[test]
    fn plain_tcp_beyond_loopback_is_found_and_loopback_and_tls_are_not() {
        let v = |xs: &[&str]| xs.iter().map(|x| x.to_string()).collect::<Vec<_>>();
        for ok in [
            "tcp/127.0.0.1:7447",
            "tcp/127.8.9.1:0",
            "tcp/[::1]:7447",
            "tcp/localhost:7447",
            "tcp/LOCALHOST:1",
            "tls/0.0.0.0:7447",
            "tls/192.0.2.7:7447",
        ] {
            assert_eq!(plain_beyond_loopback(&v(&[ok])), None, "{ok}");
        }
        for bad in [
            "tcp/0.0.0.0:7447",
            "tcp/[::]:7447",
            "tcp/192.0.2.7:7447",
            "tcp/ward-3.example.org:7447",
            "tcp/128.0.0.1:7447",
        ] {
            assert_eq!(
                plain_beyond_loopback(&v(&["tcp/127.0.0.1:1", bad])),
                Some(bad),
                "{bad}"
            );
        }
        // The default is this machine's; the scene's key is off unless set.
        let r = parse("role = \"source\"\n").unwrap();
        assert_eq!(plain_beyond_loopback(&r.listen()), None);
        assert!(!r.insecure_lab_network);
        let r = parse("role = \"source\"\ninsecure_lab_network = true\n").unwrap();
        assert!(r.insecure_lab_network);
    }

    #[test]
    fn a_client_site_syncs_with_the_relay_unless_told_otherwise() {
        let client = "role = \"observer\"\nmode = \"client\"\nconnect = [\"tcp/10.0.0.2:7447\"]\n";
        assert_eq!(parse(client).unwrap().clock(), ClockSync::Relay);
        let r = parse(&format!("{client}clock = \"source\"\n")).unwrap();
        assert_eq!(r.clock(), ClockSync::Source);
        let peer = "role = \"site\"\nconnect = [\"tcp/10.0.0.2:7447\"]\n";
        assert_eq!(parse(peer).unwrap().clock(), ClockSync::Source);
    }

    #[test]
    fn bad_values_are_refused_naming_the_key() {
        for (text, word) in [
            ("role = \"teacher\"\n", "teacher"),
            (
                "role = \"source\"\nlisten = [\"udp/0.0.0.0:7447\"]\n",
                "listen",
            ),
            (
                "role = \"source\"\nlisten = [\"tcp/0.0.0.0\"]\n",
                "tcp/HOST:PORT",
            ),
            (
                "role = \"source\"\nlisten = [\"tcp/0.0.0.0:99999\"]\n",
                "listen",
            ),
            ("role = \"site\"\nconnect = [\"tcp/:7447\"]\n", "connect"),
            ("role = \"source\"\nmode = \"client\"\n", "needs connect"),
            (
                "role = \"source\"\nmode = \"router\"\nlisten = []\n",
                "needs listen",
            ),
            ("role = \"source\"\nmode = \"mesh\"\n", "mesh"),
            ("role = \"source\"\nlease_ms = 5\n", "lease_ms"),
            ("role = \"source\"\nroom = \"a/b\"\n", "room"),
            ("role = \"source\"\nsite_id = \"xyz\"\n", "site_id"),
            ("role = \"source\"\nsite_id = \"0\"\n", "site_id"),
            ("role = \"source\"\nport = 7447\n", "port"),
            ("role = \"source\"\nclock = \"relay\"\n", "site's key"),
            (
                "role = \"site\"\nconnect = [\"tcp/10.0.0.2:7447\"]\nclock = \"relay\"\n",
                "needs mode = \"client\"",
            ),
            (
                "role = \"site\"\nconnect = [\"tcp/10.0.0.2:7447\"]\nclock = \"ntp\"\n",
                "ntp",
            ),
            (
                "role = \"observer\"\nmode = \"router\"\nconnect = [\"tcp/10.0.0.2:7447\"]\n\
                 listen = [\"tcp/0.0.0.0:7447\"]\n",
                "remote serve --mode router",
            ),
        ] {
            let e = parse(text).unwrap_err();
            assert!(e.contains(word), "{text}: {e}");
        }
    }
}
