//! python-can's `udp_multicast` interface, so python-can / python-canopen rigs share a bus
//! with axiscomp (DESIGN §6).
//!
//! Wire format (python-can 4.x, `can/interfaces/udp_multicast/utils.py`): one CAN message per
//! UDP datagram sent to a multicast group, the datagram being one MessagePack map
//! (`msgpack.packb(..., use_bin_type=True)`) with these keys, in this order:
//!
//! | key | type | our value when sending |
//! |---|---|---|
//! | `timestamp` | float64 | seconds since the Unix epoch |
//! | `arbitration_id` | int | the identifier |
//! | `is_extended_id` | bool | 29-bit identifier |
//! | `is_remote_frame` | bool | RTR |
//! | `is_error_frame` | bool | false |
//! | `channel` | nil / str / int | nil |
//! | `dlc` | int | data length (requested length for RTR) |
//! | `data` | bin | the data (empty for RTR) |
//! | `is_fd` | bool | false |
//! | `bitrate_switch` | bool | false |
//! | `error_state_indicator` | bool | false |
//!
//! python-can builds `can.Message(check=True, **map)` from a received map, replacing the
//! timestamp, so every key we send must be one of these and the values must pass its checks.
//!
//! Decoding here accepts the keys in any order and ignores unknown keys; `arbitration_id` is
//! required and the other keys default as in `can.Message` (`is_extended_id` true, flags false,
//! `dlc` = data length). A received CAN FD or error frame is well-formed but not a classic
//! frame: it is skipped (python-can with `fd=False` skips FD frames the same way). Anything
//! else that does not decode, or breaks `can.Message`'s checks (identifier range, DLC ≤ 8 and
//! equal to the data length, no data in a remote frame), is [`CanError::Malformed`].
//!
//! Sockets. python-can binds one socket to the group's port (`SO_REUSEADDR`, `SO_REUSEPORT`),
//! joins the group and sends from that same socket with multicast loopback on, so it hears its
//! own messages. We instead receive on one socket (bound to group:port, joined on `iface`) and
//! send from a second one bound to an ephemeral port on `iface`; a datagram whose source is
//! our sending socket's address is our own and is dropped, so this endpoint does not hear
//! itself while other endpoints on the same host (python-can or axiscomp) do. Setting
//! `IP_MULTICAST_IF` to `iface` makes the group usable on `lo` (tests use 127.0.0.1). With
//! `iface` = 0.0.0.0 the kernel picks the interface and own datagrams are recognised by the
//! sending port alone.
//!
//! A received datagram that does not decode is returned as [`CanError::Malformed`] by `recv`;
//! the transport keeps working and the next `recv` reads the next datagram (see
//! [`CanError::is_transient`]).

use super::msgpack::{self, Value};
use super::{CanError, CanFrame, CanTransport, MAX_EXTENDED_ID, MAX_STANDARD_ID};
use std::io;
use std::net::{Ipv4Addr, SocketAddr, SocketAddrV4};
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd};
use std::time::{SystemTime, UNIX_EPOCH};
use tokio::net::UdpSocket;
use tokio::sync::Mutex;

/// python-can's default IPv4 group (`UdpMulticastBus.DEFAULT_GROUP_IPv4`).
pub const DEFAULT_GROUP: Ipv4Addr = Ipv4Addr::new(239, 74, 163, 2);
/// python-can's default port.
pub const DEFAULT_PORT: u16 = 43113;
/// python-can's receive buffer (`max_buffer`); our own datagrams are far smaller.
pub const MAX_DATAGRAM: usize = 4096;

/// The message keys, in python-can's order.
const KEYS: [&str; 11] = [
    "timestamp",
    "arbitration_id",
    "is_extended_id",
    "is_remote_frame",
    "is_error_frame",
    "channel",
    "dlc",
    "data",
    "is_fd",
    "bitrate_switch",
    "error_state_indicator",
];

/// Encode `frame` as python-can's `pack_message` would encode the equivalent `can.Message`
/// with this `timestamp` and `channel=None`.
pub fn encode_message(frame: &CanFrame, timestamp: f64) -> Result<Vec<u8>, CanError> {
    let values = [
        Value::Float(timestamp),
        Value::Int(frame.id() as i128),
        Value::Bool(frame.is_extended()),
        Value::Bool(frame.is_remote()),
        Value::Bool(false),
        Value::Nil,
        Value::Int(frame.len() as i128),
        Value::Bin(frame.data()),
        Value::Bool(false),
        Value::Bool(false),
        Value::Bool(false),
    ];
    let map = Value::Map(KEYS.iter().map(|k| Value::Str(k)).zip(values).collect());
    let mut out = Vec::with_capacity(192);
    msgpack::encode(&map, &mut out)?;
    Ok(out)
}

fn bad(msg: String) -> CanError {
    CanError::Malformed(format!("python-can message: {msg}"))
}

/// The known keys of a received map, each found at most once.
#[derive(Default)]
struct Fields<'v, 'a> {
    found: [Option<&'v Value<'a>>; KEYS.len()],
}

impl<'v, 'a> Fields<'v, 'a> {
    fn read(v: &'v Value<'a>) -> Result<Self, CanError> {
        let Value::Map(entries) = v else {
            return Err(bad(format!("expected a map, got {}", v.kind())));
        };
        let mut f = Fields::default();
        for (k, val) in entries {
            let Value::Str(name) = k else {
                return Err(bad(format!("map key is {}, not str", k.kind())));
            };
            if let Some(i) = KEYS.iter().position(|known| known == name)
                && f.found[i].replace(val).is_some()
            {
                return Err(bad(format!("key `{name}` repeats")));
            }
        }
        Ok(f)
    }

    fn get(&self, key: &str) -> Option<&'v Value<'a>> {
        KEYS.iter()
            .position(|k| *k == key)
            .and_then(|i| self.found[i])
    }

    fn bool(&self, key: &str, default: bool) -> Result<bool, CanError> {
        match self.get(key) {
            None => Ok(default),
            Some(Value::Bool(b)) => Ok(*b),
            Some(v) => Err(bad(format!("`{key}` is {}, not bool", v.kind()))),
        }
    }
}

/// Decode one datagram. `Ok(None)`: a well-formed CAN FD or error frame, which a classic
/// transport skips.
pub fn decode_message(buf: &[u8]) -> Result<Option<CanFrame>, CanError> {
    let v = msgpack::decode(buf)?;
    let f = Fields::read(&v)?;
    let id = match f.get("arbitration_id") {
        None => return Err(bad("no `arbitration_id`".into())),
        Some(Value::Int(i)) => *i,
        Some(v) => return Err(bad(format!("`arbitration_id` is {}, not int", v.kind()))),
    };
    let extended = f.bool("is_extended_id", true)?;
    let remote = f.bool("is_remote_frame", false)?;
    let error = f.bool("is_error_frame", false)?;
    let fd = f.bool("is_fd", false)?;
    let data: &[u8] = match f.get("data") {
        None | Some(Value::Nil) => &[],
        Some(Value::Bin(b)) => b,
        Some(v) => return Err(bad(format!("`data` is {}, not bin", v.kind()))),
    };
    let dlc = match f.get("dlc") {
        None | Some(Value::Nil) => data.len() as i128,
        Some(Value::Int(i)) => *i,
        Some(v) => return Err(bad(format!("`dlc` is {}, not int", v.kind()))),
    };
    if error || fd {
        return Ok(None);
    }
    let max = if extended {
        MAX_EXTENDED_ID
    } else {
        MAX_STANDARD_ID
    };
    if !(0..=max as i128).contains(&id) {
        let kind = if extended { "extended" } else { "standard" };
        return Err(bad(format!(
            "{kind} arbitration_id {id:#x} out of range 0 to {max:#x}"
        )));
    }
    if !(0..=8).contains(&dlc) {
        return Err(bad(format!("dlc {dlc} out of range 0 to 8")));
    }
    let frame = if remote {
        if !data.is_empty() {
            return Err(bad(format!(
                "remote frame carries {} data bytes",
                data.len()
            )));
        }
        CanFrame::remote(id as u32, extended, dlc as u8)
    } else {
        if dlc != data.len() as i128 {
            return Err(bad(format!(
                "dlc {dlc} differs from the data length {}",
                data.len()
            )));
        }
        CanFrame::with_id(id as u32, extended, data)
    };
    // Unreachable after the checks above; kept as an error rather than a panic.
    frame
        .map(Some)
        .ok_or_else(|| bad(format!("frame {id:#x}/{dlc} not representable")))
}

/// A node on a python-can `udp_multicast` bus (IPv4).
#[derive(Debug)]
pub struct PyCanMulticast {
    rx: UdpSocket,
    tx: UdpSocket,
    dest: SocketAddr,
    own: SocketAddr,
    buf: Mutex<Vec<u8>>,
}

fn io_err(what: &str, e: io::Error) -> CanError {
    CanError::Io(format!("udp multicast: {what}: {e}"))
}

impl PyCanMulticast {
    /// Join `group`:`port` on the interface with address `iface` (python-can's defaults are
    /// [`DEFAULT_GROUP`] and [`DEFAULT_PORT`]; tests use 127.0.0.1 on loopback). Must be
    /// called within a tokio runtime.
    pub async fn open(
        group: Ipv4Addr,
        port: u16,
        iface: Ipv4Addr,
    ) -> Result<PyCanMulticast, CanError> {
        if !group.is_multicast() {
            return Err(CanError::Io(format!(
                "udp multicast: {group} is not a multicast group (224.0.0.0/4)"
            )));
        }
        let rx = sock::receiver(group, port, iface).map_err(|e| io_err("receiver", e))?;
        let tx = sock::sender(iface, port).map_err(|e| io_err("sender", e))?;
        let own = tx.local_addr().map_err(|e| io_err("sender address", e))?;
        let rx = UdpSocket::from_std(rx).map_err(|e| io_err("receiver", e))?;
        let tx = UdpSocket::from_std(tx).map_err(|e| io_err("sender", e))?;
        tracing::debug!(%group, port, %iface, %own, "python-can udp_multicast bus joined");
        Ok(PyCanMulticast {
            rx,
            tx,
            dest: SocketAddr::V4(SocketAddrV4::new(group, port)),
            own,
            buf: Mutex::new(vec![0; MAX_DATAGRAM]),
        })
    }

    /// The address our datagrams come from (what other nodes see as the source).
    pub fn local_addr(&self) -> SocketAddr {
        self.own
    }

    fn is_own(&self, src: SocketAddr) -> bool {
        src.port() == self.own.port()
            && (self.own.ip().is_unspecified() || src.ip() == self.own.ip())
    }
}

impl CanTransport for PyCanMulticast {
    async fn send(&self, frame: &CanFrame) -> Result<(), CanError> {
        let now = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map(|d| d.as_secs_f64())
            .unwrap_or(0.0);
        let bytes = encode_message(frame, now)?;
        let n = self
            .tx
            .send_to(&bytes, self.dest)
            .await
            .map_err(|e| io_err("send", e))?;
        if n != bytes.len() {
            return Err(CanError::Io(format!(
                "udp multicast: sent {n} of {} bytes",
                bytes.len()
            )));
        }
        Ok(())
    }

    /// Cancel-safe: the awaits are the buffer's lock and the socket's `recv_from`, both
    /// cancel-safe; decoding after a datagram arrives is synchronous.
    async fn recv(&self) -> Result<CanFrame, CanError> {
        let mut buf = self.buf.lock().await;
        loop {
            let (n, src) = self
                .rx
                .recv_from(&mut buf)
                .await
                .map_err(|e| io_err("receive", e))?;
            if self.is_own(src) {
                continue;
            }
            match decode_message(&buf[..n]) {
                Ok(Some(frame)) => return Ok(frame),
                Ok(None) => {
                    tracing::debug!(%src, "skipped a CAN FD or error frame");
                }
                Err(e) => {
                    tracing::warn!(%src, "{e}");
                    return Err(e);
                }
            }
        }
    }
}

/// Socket set-up the standard library cannot express (options before `bind`,
/// `IP_MULTICAST_IF`, `IP_MULTICAST_ALL`), with `libc`.
mod sock {
    use super::*;
    use crate::util::sock::{check, set_int};

    fn in_addr(a: Ipv4Addr) -> libc::in_addr {
        libc::in_addr {
            s_addr: u32::from_ne_bytes(a.octets()),
        }
    }

    fn set_multicast_if(fd: &OwnedFd, iface: Ipv4Addr) -> io::Result<()> {
        let a = in_addr(iface);
        // SAFETY: `fd` is an open socket; the value is a live in_addr of the size given.
        check(unsafe {
            libc::setsockopt(
                fd.as_raw_fd(),
                libc::IPPROTO_IP,
                libc::IP_MULTICAST_IF,
                (&a as *const libc::in_addr).cast(),
                std::mem::size_of::<libc::in_addr>() as libc::socklen_t,
            )
        })
    }

    fn udp_socket() -> io::Result<OwnedFd> {
        // SAFETY: plain socket(2) call; the result is checked before use.
        let fd = unsafe {
            libc::socket(
                libc::AF_INET,
                libc::SOCK_DGRAM | libc::SOCK_CLOEXEC | libc::SOCK_NONBLOCK,
                0,
            )
        };
        check(fd)?;
        // SAFETY: `fd` was just returned by socket(2) and is owned by nobody else.
        Ok(unsafe { OwnedFd::from_raw_fd(fd) })
    }

    fn bind(fd: &OwnedFd, addr: SocketAddrV4) -> io::Result<()> {
        let sa = libc::sockaddr_in {
            sin_family: libc::AF_INET as libc::sa_family_t,
            sin_port: addr.port().to_be(),
            sin_addr: in_addr(*addr.ip()),
            sin_zero: [0; 8],
        };
        // SAFETY: `fd` is an open socket; `sa` is a live sockaddr_in of the size given.
        check(unsafe {
            libc::bind(
                fd.as_raw_fd(),
                (&sa as *const libc::sockaddr_in).cast(),
                std::mem::size_of::<libc::sockaddr_in>() as libc::socklen_t,
            )
        })
    }

    /// Bound to group:port (so only that group's datagrams arrive), shareable with other
    /// nodes on this host, joined on `iface`.
    pub(super) fn receiver(
        group: Ipv4Addr,
        port: u16,
        iface: Ipv4Addr,
    ) -> io::Result<std::net::UdpSocket> {
        let fd = udp_socket()?;
        set_int(&fd, libc::SOL_SOCKET, libc::SO_REUSEADDR, 1)?;
        set_int(&fd, libc::SOL_SOCKET, libc::SO_REUSEPORT, 1)?;
        set_int(&fd, libc::IPPROTO_IP, libc::IP_MULTICAST_ALL, 0)?;
        bind(&fd, SocketAddrV4::new(group, port))?;
        let s = std::net::UdpSocket::from(fd);
        s.join_multicast_v4(&group, &iface)?;
        Ok(s)
    }

    /// Bound to an ephemeral port on `iface` (never the bus port, so our datagrams are
    /// told apart from python-can's, which come from the bus port), sending on `iface`,
    /// hop limit 1 as python-can's default, loopback on so local nodes hear us.
    pub(super) fn sender(iface: Ipv4Addr, bus_port: u16) -> io::Result<std::net::UdpSocket> {
        for _ in 0..4 {
            let fd = udp_socket()?;
            if !iface.is_unspecified() {
                set_multicast_if(&fd, iface)?;
            }
            bind(&fd, SocketAddrV4::new(iface, 0))?;
            let s = std::net::UdpSocket::from(fd);
            if s.local_addr()?.port() == bus_port {
                continue;
            }
            s.set_multicast_ttl_v4(1)?;
            s.set_multicast_loop_v4(true)?;
            return Ok(s);
        }
        Err(io::Error::new(
            io::ErrorKind::AddrInUse,
            "no ephemeral port apart from the bus port",
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hex(s: &str) -> Vec<u8> {
        (0..s.len())
            .step_by(2)
            .map(|i| u8::from_str_radix(&s[i..i + 2], 16).unwrap())
            .collect()
    }

    // The datagrams below were produced on this machine with python-can 4.6.1 and msgpack
    // 1.2.4:
    //   from can import Message
    //   from can.interfaces.udp_multicast.utils import pack_message
    //   print(pack_message(Message(...)).hex())
    // with the Message arguments written above each constant.

    /// timestamp=1700000000.25, arbitration_id=0x181, is_extended_id=False,
    /// data=[1,2,3,4,5,6,7,8]
    const PY_STD: &str = "8ba974696d657374616d70cb41d954fc40100000ae6172626974726174696f6e5f6964cd0181ae69735f657874656e6465645f6964c2af69735f72656d6f74655f6672616d65c2ae69735f6572726f725f6672616d65c2a76368616e6e656cc0a3646c6308a464617461c4080102030405060708a569735f6664c2ae626974726174655f737769746368c2b56572726f725f73746174655f696e64696361746f72c2";
    /// timestamp=0.5, arbitration_id=0x1ABCDEF0, is_extended_id=True, data=[0xff]
    const PY_EXT: &str = "8ba974696d657374616d70cb3fe0000000000000ae6172626974726174696f6e5f6964ce1abcdef0ae69735f657874656e6465645f6964c3af69735f72656d6f74655f6672616d65c2ae69735f6572726f725f6672616d65c2a76368616e6e656cc0a3646c6301a464617461c401ffa569735f6664c2ae626974726174655f737769746368c2b56572726f725f73746174655f696e64696361746f72c2";
    /// timestamp=2.0, arbitration_id=0x701, is_extended_id=False, is_remote_frame=True, dlc=1
    const PY_RTR: &str = "8ba974696d657374616d70cb4000000000000000ae6172626974726174696f6e5f6964cd0701ae69735f657874656e6465645f6964c2af69735f72656d6f74655f6672616d65c3ae69735f6572726f725f6672616d65c2a76368616e6e656cc0a3646c6301a464617461c400a569735f6664c2ae626974726174655f737769746368c2b56572726f725f73746174655f696e64696361746f72c2";
    /// timestamp=3.0, arbitration_id=0x123, is_extended_id=False, is_fd=True,
    /// bitrate_switch=True, data=bytes(range(12))
    const PY_FD: &str = "8ba974696d657374616d70cb4008000000000000ae6172626974726174696f6e5f6964cd0123ae69735f657874656e6465645f6964c2af69735f72656d6f74655f6672616d65c2ae69735f6572726f725f6672616d65c2a76368616e6e656cc0a3646c630ca464617461c40c000102030405060708090a0ba569735f6664c3ae626974726174655f737769746368c3b56572726f725f73746174655f696e64696361746f72c2";
    /// timestamp=4.0, arbitration_id=0x20000004, is_extended_id=True, is_error_frame=True,
    /// data=bytes(8)
    const PY_ERR: &str = "8ba974696d657374616d70cb4010000000000000ae6172626974726174696f6e5f6964ce20000004ae69735f657874656e6465645f6964c3af69735f72656d6f74655f6672616d65c2ae69735f6572726f725f6672616d65c3a76368616e6e656cc0a3646c6308a464617461c4080000000000000000a569735f6664c2ae626974726174655f737769746368c2b56572726f725f73746174655f696e64696361746f72c2";
    /// timestamp=0.0, arbitration_id=0, is_extended_id=False, data=[], channel="vcan0"
    const PY_EMPTY_CHAN: &str = "8ba974696d657374616d70cb0000000000000000ae6172626974726174696f6e5f696400ae69735f657874656e6465645f6964c2af69735f72656d6f74655f6672616d65c2ae69735f6572726f725f6672616d65c2a76368616e6e656ca57663616e30a3646c6300a464617461c400a569735f6664c2ae626974726174655f737769746368c2b56572726f725f73746174655f696e64696361746f72c2";
    /// Not pack_message: `msgpack.packb({"data": b"\x10\x20", "x-extra": [1, {"k": None}],
    /// "dlc": 2, "arbitration_id": 0x7ff, "is_extended_id": False, "timestamp": 7},
    /// use_bin_type=True)` — other key order, an extra key, missing optional keys.
    const PY_REORDERED: &str = "86a464617461c4021020a7782d6578747261920181a16bc0a3646c6302ae6172626974726174696f6e5f6964cd07ffae69735f657874656e6465645f6964c2a974696d657374616d7007";

    #[test]
    fn python_datagrams_decode() {
        let f = decode_message(&hex(PY_STD)).unwrap().unwrap();
        assert_eq!(f, CanFrame::new(0x181, &[1, 2, 3, 4, 5, 6, 7, 8]).unwrap());
        let f = decode_message(&hex(PY_EXT)).unwrap().unwrap();
        assert_eq!(f, CanFrame::new_extended(0x1ABC_DEF0, &[0xff]).unwrap());
        let f = decode_message(&hex(PY_RTR)).unwrap().unwrap();
        assert_eq!(f, CanFrame::remote(0x701, false, 1).unwrap());
        let f = decode_message(&hex(PY_EMPTY_CHAN)).unwrap().unwrap();
        assert_eq!(f, CanFrame::new(0, &[]).unwrap());
        let f = decode_message(&hex(PY_REORDERED)).unwrap().unwrap();
        assert_eq!(f, CanFrame::new(0x7ff, &[0x10, 0x20]).unwrap());
    }

    #[test]
    fn fd_and_error_frames_are_skipped() {
        assert_eq!(decode_message(&hex(PY_FD)).unwrap(), None);
        assert_eq!(decode_message(&hex(PY_ERR)).unwrap(), None);
    }

    #[test]
    fn encoding_is_byte_identical_to_python_can() {
        let f = CanFrame::new(0x181, &[1, 2, 3, 4, 5, 6, 7, 8]).unwrap();
        assert_eq!(encode_message(&f, 1_700_000_000.25).unwrap(), hex(PY_STD));
        let f = CanFrame::new_extended(0x1ABC_DEF0, &[0xff]).unwrap();
        assert_eq!(encode_message(&f, 0.5).unwrap(), hex(PY_EXT));
        let f = CanFrame::remote(0x701, false, 1).unwrap();
        assert_eq!(encode_message(&f, 2.0).unwrap(), hex(PY_RTR));
    }

    /// Replace the value bytes `from` by `to` once in a python datagram.
    fn patched(base: &str, from: &str, to: &str) -> Vec<u8> {
        assert_eq!(base.matches(from).count(), 1, "{from} must occur once");
        hex(&base.replacen(from, to, 1))
    }

    fn malformed(buf: &[u8]) -> String {
        match decode_message(buf) {
            Err(CanError::Malformed(m)) => m,
            other => panic!("expected Malformed, got {other:?}"),
        }
    }

    #[test]
    fn malformed_messages_are_refused_with_the_reason() {
        // "dlc" 08 -> 07 while 8 data bytes follow
        let m = malformed(&patched(PY_STD, "a3646c6308", "a3646c6307"));
        assert!(m.contains("dlc 7 differs"), "{m}");
        // a standard id of 0x800 ("arbitration_id" cd0181 -> cd0800)
        let m = malformed(&patched(PY_STD, "cd0181", "cd0800"));
        assert!(m.contains("standard arbitration_id 0x800"), "{m}");
        // an extended id of 2^29 (ce1abcdef0 -> ce20000000)
        let m = malformed(&patched(PY_EXT, "ce1abcdef0", "ce20000000"));
        assert!(m.contains("extended arbitration_id"), "{m}");
        // a remote frame carrying one data byte (data c400 -> c40155)
        let m = malformed(&patched(PY_RTR, "c400a569", "c40155a569"));
        assert!(m.contains("remote frame carries 1"), "{m}");
        // "is_extended_id" as int 1 instead of bool (c3 -> 01)
        let m = malformed(&patched(PY_EXT, "6964c3", "696401"));
        assert!(m.contains("`is_extended_id` is int"), "{m}");
        // negative dlc (08 -> ff = -1)
        let m = malformed(&patched(PY_STD, "a3646c6308", "a3646c63ff"));
        assert!(m.contains("dlc -1"), "{m}");
        // no arbitration_id: {"data": b""}
        let m = malformed(&hex("81a464617461c400"));
        assert!(m.contains("no `arbitration_id`"), "{m}");
        // not a map: the integer 1
        assert!(malformed(&hex("01")).contains("expected a map"));
        // a non-str key: {1: 2}
        assert!(malformed(&hex("810102")).contains("map key is int"));
        // a repeated known key: {"dlc": 0, "dlc": 0, "arbitration_id": 1}
        let m = malformed(&hex(
            "83a3646c6300a3646c6300ae6172626974726174696f6e5f696401",
        ));
        assert!(m.contains("`dlc` repeats"), "{m}");
        // truncated datagram: the python one minus its last byte
        let mut t = hex(PY_STD);
        t.pop();
        assert!(malformed(&t).contains("truncated"));
    }
}
