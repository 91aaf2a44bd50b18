//! The networks a listening input serves: loopback always, and the addresses or networks the
//! operator names (`--igtl-allow`, `[tracker] allow`). Shared by the OpenIGTLink server and the
//! UDP respiratory signal, so both refuse the same strangers.

/// The networks a sender may connect from: loopback always, and these.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct AllowList {
    nets: Vec<ipnet::IpNet>,
}

impl AllowList {
    /// From `--igtl-allow` values: an address (`10.0.0.5`, `fe80::1`) or a network
    /// (`10.0.0.0/24`).
    pub fn parse(items: &[String]) -> Result<Self, String> {
        Self::parse_as(items, "--igtl-allow")
    }

    /// [`Self::parse`], naming `option` (where the values came from) in its errors.
    pub fn parse_as(items: &[String], option: &str) -> Result<Self, String> {
        let mut nets = Vec::with_capacity(items.len());
        for item in items {
            let t = item.trim();
            let net = match t.parse::<ipnet::IpNet>() {
                Ok(n) => n.trunc(),
                Err(_) => match t.parse::<std::net::IpAddr>() {
                    Ok(ip) => ipnet::IpNet::from(ip),
                    Err(_) => {
                        return Err(format!(
                            "{option} {t:?}: not an address or network (write 10.0.0.5 or \
                             10.0.0.0/24; host names are not taken: a name can change what it means)"
                        ))
                    }
                },
            };
            if net.prefix_len() == 0 {
                return Err(format!(
                    "{option} {t:?} admits every host: name the address of the computer that \
                     connects, or its network, instead"
                ));
            }
            nets.push(net);
        }
        Ok(Self { nets })
    }

    /// Whether a sender at `ip` is served (an IPv4 address seen as IPv6-mapped counts as IPv4).
    pub fn allows(&self, ip: std::net::IpAddr) -> bool {
        let ip = match ip {
            std::net::IpAddr::V6(v6) => v6.to_ipv4_mapped().map(std::net::IpAddr::V4).unwrap_or(ip),
            v4 => v4,
        };
        ip.is_loopback() || self.nets.iter().any(|n| n.contains(&ip))
    }

    /// The list in words (start-up, JSON).
    pub fn describe(&self) -> String {
        let mut words = vec!["loopback".to_string()];
        words.extend(self.nets.iter().map(|n| {
            if n.prefix_len() == n.max_prefix_len() {
                n.addr().to_string()
            } else {
                n.to_string()
            }
        }));
        words.join(", ")
    }
}
