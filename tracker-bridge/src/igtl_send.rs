//! What lungdyn sends over OpenIGTLink (to 3D Slicer, `lungdyn demo --igtl-serve`): whole
//! version-1 messages appended to one reused buffer — the header's 58 bytes reserved, the content
//! appended, then sealed in place with its size and CRC ([`crate::igtl::seal`]). Once the buffer has
//! grown to a frame's size nothing allocates.
//!
//! STRING content (the OpenIGTLink v2 protocol text, `igtl_string.h`): `u16` encoding as an IANA
//! MIBenum (3 = US-ASCII, 106 = UTF-8), `u16` length, the bytes, no NUL. TRANSFORM content: the 12
//! values of [`crate::igtl::Transform::to_wire`]. POLYDATA: [`crate::igtl_polydata`].

use thiserror::Error;

use crate::igtl::{seal, seal_with_crc, IgtlError, Timestamp, Transform, HEADER_SIZE};
use crate::igtl_polydata::{FixedMesh, PointScalars, PolyDataError, Topology};

/// MIBenum of US-ASCII.
pub const US_ASCII: u16 = 3;
/// MIBenum of UTF-8.
pub const UTF_8: u16 = 106;

/// Why a message cannot be made (nothing is appended then).
#[derive(Debug, Error)]
pub enum SendError {
    /// The mesh.
    #[error(transparent)]
    PolyData(#[from] PolyDataError),
    /// The header (a bad device name).
    #[error(transparent)]
    Igtl(#[from] IgtlError),
    /// A STRING longer than its 16-bit length.
    #[error("a STRING message holds at most 65535 bytes, not {0}")]
    StringTooLong(usize),
    /// A TRANSFORM with a NaN or infinite value.
    #[error("the {0} transform is not finite")]
    NotFinite(String),
}

/// Appends one message: reserves the header, lets `content` append the body, seals it; on an error
/// `out` is as it was.
fn framed(
    out: &mut Vec<u8>,
    type_name: &str,
    device: &str,
    timestamp: Timestamp,
    content: impl FnOnce(&mut Vec<u8>) -> Result<(), SendError>,
) -> Result<(), SendError> {
    let start = out.len();
    out.resize(start + HEADER_SIZE, 0);
    let sealed = content(out).and_then(|()| {
        seal(&mut out[start..], type_name, device, timestamp).map_err(SendError::from)
    });
    if sealed.is_err() {
        out.truncate(start);
    }
    sealed
}

/// A POLYDATA message of `points` over `topology` with `scalars`.
pub fn polydata(
    out: &mut Vec<u8>,
    device: &str,
    timestamp: Timestamp,
    points: &[[f32; 3]],
    topology: &Topology,
    scalars: &[PointScalars<'_>],
) -> Result<(), SendError> {
    framed(
        out,
        crate::igtl_polydata::TYPE_NAME,
        device,
        timestamp,
        |o| crate::igtl_polydata::append(points, topology, scalars, o).map_err(SendError::from),
    )
}

/// A POLYDATA message of `points` over a [`FixedMesh`] (its triangles and scalars encoded and CRC'd
/// once): the same bytes as [`polydata`], with only the points encoded and CRC'd per call.
pub fn fixed_polydata(
    out: &mut Vec<u8>,
    device: &str,
    timestamp: Timestamp,
    points: &[[f32; 3]],
    mesh: &FixedMesh,
) -> Result<(), SendError> {
    let start = out.len();
    out.resize(start + HEADER_SIZE, 0);
    let sealed = mesh
        .append(points, out)
        .map_err(SendError::from)
        .and_then(|crc| {
            seal_with_crc(
                &mut out[start..],
                crate::igtl_polydata::TYPE_NAME,
                device,
                timestamp,
                crc,
            )
            .map_err(SendError::from)
        });
    if sealed.is_err() {
        out.truncate(start);
    }
    sealed
}

/// A STRING message of `text` (US-ASCII when it is, else UTF-8).
pub fn string(
    out: &mut Vec<u8>,
    device: &str,
    timestamp: Timestamp,
    text: &str,
) -> Result<(), SendError> {
    let len = u16::try_from(text.len()).map_err(|_| SendError::StringTooLong(text.len()))?;
    framed(out, "STRING", device, timestamp, |o| {
        let encoding = if text.is_ascii() { US_ASCII } else { UTF_8 };
        o.extend_from_slice(&encoding.to_be_bytes());
        o.extend_from_slice(&len.to_be_bytes());
        o.extend_from_slice(text.as_bytes());
        Ok(())
    })
}

/// A TRANSFORM message.
pub fn transform(
    out: &mut Vec<u8>,
    device: &str,
    timestamp: Timestamp,
    t: &Transform,
) -> Result<(), SendError> {
    let wire = t.to_wire();
    if !wire.iter().all(|v| v.is_finite()) {
        return Err(SendError::NotFinite(device.to_string()));
    }
    framed(out, "TRANSFORM", device, timestamp, |o| {
        for v in wire {
            o.extend_from_slice(&v.to_be_bytes());
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::igtl::{Body, Limits, Message};

    fn limits() -> Limits {
        Limits {
            max_body_bytes: 64 << 20,
            ..Limits::default()
        }
    }

    /// Messages appended back to back decode, with our own reader, to what was sent: the header's
    /// names, timestamp, size and CRC are those of the body.
    #[test]
    fn appended_messages_decode_back_to_back() {
        let mut out = Vec::new();
        let ts = Timestamp::from_parts(1_700_000_000, 1 << 31);
        let t = Transform {
            rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            translation_mm: [-12.5, 30.0, 101.25],
        };
        transform(&mut out, "Tumour", ts, &t).unwrap();
        string(&mut out, "BreathState", ts, "{\"tick\":5}").unwrap();
        let topo = Topology::triangles(&[[0, 1, 2]], 3).unwrap();
        let pts = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        polydata(&mut out, "RightLung", ts, &pts, &topo, &[]).unwrap();
        let (m, n) = Message::decode(&out, &limits()).unwrap();
        assert_eq!((m.device_name.as_str(), m.timestamp), ("Tumour", ts));
        assert_eq!(m.body, Body::Transform(t));
        let (m2, n2) = Message::decode(&out[n..], &limits()).unwrap();
        assert_eq!(m2.device_name, "BreathState");
        assert_eq!(m2.body.type_name(), "STRING");
        // STRING is not a type our reader parses (it is skipped): check its bytes by hand.
        let body = &out[n + HEADER_SIZE..n + n2];
        assert_eq!(&body[..4], &[0, 3, 0, 10]);
        assert_eq!(&body[4..], b"{\"tick\":5}");
        let (m3, n3) = Message::decode(&out[n + n2..], &limits()).unwrap();
        assert_eq!(m3.body.type_name(), "POLYDATA");
        assert_eq!(n + n2 + n3, out.len());
    }

    #[test]
    fn utf8_text_says_so_and_an_overlong_string_is_refused_leaving_the_buffer_alone() {
        let mut out = vec![7u8];
        string(&mut out, "S", Timestamp(1), "Lunge – rechts").unwrap();
        assert_eq!(
            &out[1 + HEADER_SIZE..1 + HEADER_SIZE + 2],
            &UTF_8.to_be_bytes()
        );
        let before = out.clone();
        let long = "x".repeat(70_000);
        assert!(matches!(
            string(&mut out, "S", Timestamp(1), &long),
            Err(SendError::StringTooLong(70_000))
        ));
        assert_eq!(out, before);
    }

    #[test]
    fn bad_names_and_values_append_nothing() {
        let mut out = Vec::new();
        let mut t = Transform::IDENTITY;
        assert!(string(&mut out, "a device name of 21 c", Timestamp(1), "x").is_err());
        assert!(string(&mut out, "tab\there", Timestamp(1), "x").is_err());
        t.translation_mm[1] = f32::NAN;
        assert!(matches!(
            transform(&mut out, "Tumour", Timestamp(1), &t),
            Err(SendError::NotFinite(_))
        ));
        let topo = Topology::triangles(&[[0, 1, 2]], 3).unwrap();
        let bad = [[0.0, 0.0, 0.0], [f32::INFINITY, 0.0, 0.0], [0.0, 1.0, 0.0]];
        assert!(polydata(&mut out, "L", Timestamp(1), &bad, &topo, &[]).is_err());
        assert!(out.is_empty());
        assert!(seal(&mut [0u8; 10], "STRING", "", Timestamp(0)).is_err());
    }

    /// A POLYDATA over a fixed mesh is the same message, byte for byte, as the plain one, and
    /// decodes with its CRC checked; on bad points the buffer is left alone.
    #[test]
    fn a_fixed_mesh_message_is_the_plain_message() {
        let topo = Topology::triangles(&[[0, 1, 2], [0, 2, 1]], 3).unwrap();
        let lobes = [1.0f32, 1.0, 2.0];
        let scalars = [PointScalars {
            name: "Lobe",
            components: 1,
            values: &lobes,
        }];
        let mesh = FixedMesh::new(&topo, &scalars).unwrap();
        let ts = Timestamp::from_parts(1_700_000_000, 7);
        let pts = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.5]];
        let mut plain = Vec::new();
        polydata(&mut plain, "LeftLung", ts, &pts, &topo, &scalars).unwrap();
        let mut fixed = Vec::new();
        fixed_polydata(&mut fixed, "LeftLung", ts, &pts, &mesh).unwrap();
        assert_eq!(fixed, plain);
        let (m, n) = Message::decode(&fixed, &limits()).unwrap();
        assert_eq!((m.body.type_name(), n), ("POLYDATA", fixed.len()));
        let bad = [[0.0, f32::INFINITY, 0.0]; 3];
        assert!(fixed_polydata(&mut fixed, "LeftLung", ts, &bad, &mesh).is_err());
        assert_eq!(fixed, plain);
    }
}
