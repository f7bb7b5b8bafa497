//! Socket options the standard library cannot set, with `libc` (shared by the python-can
//! multicast transport and the paced Modbus reader).

use std::io;
use std::os::fd::AsFd;
use std::os::fd::AsRawFd;

/// A libc return code as an `io::Result` (negative: the OS error).
pub fn check(rc: libc::c_int) -> io::Result<()> {
    if rc < 0 {
        Err(io::Error::last_os_error())
    } else {
        Ok(())
    }
}

/// `setsockopt` of an `int` option.
pub fn set_int(
    fd: &impl AsFd,
    level: libc::c_int,
    name: libc::c_int,
    v: libc::c_int,
) -> io::Result<()> {
    // SAFETY: `fd` is an open descriptor; the option value is a live c_int of the size given.
    check(unsafe {
        libc::setsockopt(
            fd.as_fd().as_raw_fd(),
            level,
            name,
            (&v as *const libc::c_int).cast(),
            std::mem::size_of::<libc::c_int>() as libc::socklen_t,
        )
    })
}
