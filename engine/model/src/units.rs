//! Units named in column headers: the tables every table reader (PV curves, ventilator recordings)
//! recognises, each with its factor to lungdyn's unit (cmH2O, ml, L/s, s, mm).

/// Pressure units recognised in a column header (token of the header, case-insensitive).
pub const PRESSURE_UNITS: &[(&str, &str, f64)] = &[
    ("cmh2o", "cmH2O", 1.0),
    ("cmh20", "cmH2O", 1.0),
    ("kpa", "kPa", 10.197_162),
    ("hpa", "hPa", 1.019_716_2),
    ("mbar", "mbar", 1.019_716_2),
    ("pa", "Pa", 0.010_197_162),
    ("mmhg", "mmHg", 1.359_51),
    ("torr", "Torr", 1.359_51),
    ("inh2o", "inH2O", 2.54),
    ("psi", "psi", 70.306_958),
];

/// Volume units recognised in a column header.
pub const VOLUME_UNITS: &[(&str, &str, f64)] = &[
    ("ml", "ml", 1.0),
    ("cc", "ml", 1.0),
    ("cm3", "ml", 1.0),
    ("l", "L", 1000.0),
    ("litre", "L", 1000.0),
    ("liter", "L", 1000.0),
    ("litres", "L", 1000.0),
    ("liters", "L", 1000.0),
    ("dl", "dL", 100.0),
];

/// Length units recognised in a column header (a chest marker's excursion), with the factor to mm.
pub const LENGTH_UNITS: &[(&str, &str, f64)] = &[
    ("mm", "mm", 1.0),
    ("cm", "cm", 10.0),
    ("m", "m", 1000.0),
    ("um", "µm", 1e-3),
];

/// The lower-case alphanumeric tokens of a column header (`"Paw (cmH2O)"` → `paw`, `cmh2o`).
pub fn tokens(header: &str) -> impl Iterator<Item = String> + '_ {
    header
        .split(|c: char| !c.is_ascii_alphanumeric())
        .filter(|t| !t.is_empty())
        .map(|t| t.to_ascii_lowercase())
}

/// The unit a header names, from `table` (the first token of the header that is a unit).
pub fn header_unit(
    header: &str,
    table: &[(&str, &'static str, f64)],
) -> Option<(&'static str, f64)> {
    tokens(header).find_map(|t| {
        table
            .iter()
            .find(|(k, _, _)| *k == t)
            .map(|(_, name, f)| (*name, *f))
    })
}

/// Flow units recognised in a column header, with the factor to L/s: `L/min`, `lpm`, `L/s`, `lps`,
/// `ml/s`, `ml/min` (also written `L_per_min`, `l min`, ...).
pub fn flow_unit(header: &str) -> Option<(&'static str, f64)> {
    let t: Vec<String> = tokens(header).filter(|t| t != "per").collect();
    t.iter()
        .enumerate()
        .find_map(|(i, tok)| match tok.as_str() {
            "lpm" | "slpm" => Some(("L/min", 1.0 / 60.0)),
            "lps" => Some(("L/s", 1.0)),
            "l" | "ml" => {
                let litres = if tok == "l" { 1.0 } else { 1e-3 };
                match t.get(i + 1).map(String::as_str) {
                    Some("min") => {
                        Some((if tok == "l" { "L/min" } else { "ml/min" }, litres / 60.0))
                    }
                    Some("s" | "sec") => Some((if tok == "l" { "L/s" } else { "ml/s" }, litres)),
                    _ => None,
                }
            }
            _ => None,
        })
}

/// Time units recognised in a column header, with the factor to seconds.
pub fn time_unit(header: &str) -> Option<(&'static str, f64)> {
    tokens(header).find_map(|t| match t.as_str() {
        "s" | "sec" | "secs" | "second" | "seconds" => Some(("s", 1.0)),
        "ms" | "msec" => Some(("ms", 1e-3)),
        "min" | "minutes" => Some(("min", 60.0)),
        _ => None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flow_and_time_units_are_read_from_headers() {
        assert_eq!(flow_unit("flow (L/min)"), Some(("L/min", 1.0 / 60.0)));
        assert_eq!(flow_unit("Flow_lpm"), Some(("L/min", 1.0 / 60.0)));
        assert_eq!(flow_unit("flow L per s"), Some(("L/s", 1.0)));
        assert_eq!(flow_unit("flow_ml_s"), Some(("ml/s", 1e-3)));
        assert_eq!(flow_unit("flow"), None);
        assert_eq!(flow_unit("flow (L)"), None, "a volume unit is no flow unit");
        assert_eq!(time_unit("time_s"), Some(("s", 1.0)));
        assert_eq!(time_unit("t [ms]"), Some(("ms", 1e-3)));
        assert_eq!(time_unit("time"), None);
        assert_eq!(
            header_unit("Paw (mbar)", PRESSURE_UNITS),
            Some(("mbar", 1.019_716_2))
        );
    }
}
