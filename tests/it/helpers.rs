//! Helpers shared by the integration tests.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};

/// The binary under test.
pub fn bin() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_axiscomp"));
    c.current_dir(env!("CARGO_MANIFEST_DIR"));
    c
}

/// Run the binary with `args`, feeding `stdin`.
pub fn run(args: &[&str], stdin: &str) -> Output {
    let mut child = bin()
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn axiscomp");
    child
        .stdin
        .take()
        .expect("stdin")
        .write_all(stdin.as_bytes())
        .expect("write stdin");
    child.wait_with_output().expect("wait axiscomp")
}

/// Standard output as text.
pub fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// Standard error as text.
pub fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// A fresh directory under the target's temporary folder, removed on drop.
pub struct TempDir(PathBuf);

impl TempDir {
    pub fn new(name: &str) -> Self {
        static N: AtomicUsize = AtomicUsize::new(0);
        let p = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!(
            "{name}-{}-{}",
            std::process::id(),
            N.fetch_add(1, Ordering::Relaxed)
        ));
        let _ = std::fs::remove_dir_all(&p);
        std::fs::create_dir_all(&p).expect("create temp dir");
        TempDir(p)
    }
    pub fn path(&self, file: &str) -> PathBuf {
        self.0.join(file)
    }
    pub fn write(&self, file: &str, text: &str) -> PathBuf {
        let p = self.path(file);
        std::fs::write(&p, text).expect("write temp file");
        p
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// The reference layout file's text.
pub fn reference_layout_text() -> String {
    std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/optics/reference.toml"),
    )
    .expect("read reference layout")
}

// ---------- Modbus / acquisition helpers ----------

use axiscomp::modbus::{Link, LinkConfig};
use axiscomp::optics::Layout;
use axiscomp::sim::iomodule::IoModule;
use axiscomp::sim::plant::{Plant, PlantSpec};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// The twin's plant with the default spec and the reference layout.
pub fn plant() -> Arc<Plant> {
    Arc::new(
        Plant::new(&Layout::reference(), &PlantSpec::default(), Instant::now())
            .expect("default plant"),
    )
}

/// The twin's I/O module serving `plant` through the generic map on a loopback port.
pub async fn twin(plant: Arc<Plant>) -> IoModule {
    IoModule::generic(plant)
        .await
        .expect("start the twin's I/O module")
}

/// A link with test-friendly timings (300 ms call timeout, backoff 50..400 ms).
pub fn link(addr: SocketAddr) -> Link {
    Link::spawn(LinkConfig {
        timeout: Duration::from_millis(300),
        backoff_max: Duration::from_millis(400),
        ..LinkConfig::new(addr)
    })
}

/// Send one raw Modbus TCP request (`pdu` after the MBAP header) and return the reply's PDU;
/// checks the reply header echoes the transaction and unit ids.
pub async fn raw_request(stream: &mut TcpStream, tid: u16, unit: u8, pdu: &[u8]) -> Vec<u8> {
    let mut req = Vec::with_capacity(7 + pdu.len());
    req.extend_from_slice(&tid.to_be_bytes());
    req.extend_from_slice(&[0, 0]);
    req.extend_from_slice(&((pdu.len() + 1) as u16).to_be_bytes());
    req.push(unit);
    req.extend_from_slice(pdu);
    let io = async {
        stream.write_all(&req).await?;
        let mut hdr = [0u8; 7];
        stream.read_exact(&mut hdr).await?;
        let len = u16::from_be_bytes([hdr[4], hdr[5]]) as usize;
        let mut body = vec![0u8; len.saturating_sub(1)];
        stream.read_exact(&mut body).await?;
        Ok::<_, std::io::Error>((hdr, body))
    };
    let (hdr, body) = tokio::time::timeout(Duration::from_secs(5), io)
        .await
        .expect("reply within 5 s")
        .expect("reply read");
    assert_eq!(u16::from_be_bytes([hdr[0], hdr[1]]), tid, "transaction id");
    assert_eq!(hdr[6], unit, "unit id");
    body
}

/// A free loopback TCP port (bound and released).
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("free port")
        .port()
}
