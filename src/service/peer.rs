//! Who is on the other end of the control socket (peer credentials, SO_PEERCRED) and what they
//! may do: viewing needs the viewer group, changing anything the operator group (DESIGN §8).
//! Root and the service's own user are operators. Group membership includes supplementary
//! groups, looked up through the C library (so NSS users and groups work).
//!
//! The socket file itself admits only the two groups (and its owner): a POSIX access ACL
//! ([`open_to_groups`]), since one file has one group and a site's viewers and operators are
//! two. Everyone else is refused by the kernel on connect.

use super::api::Role;
use serde::Serialize;
use std::ffi::{CStr, CString};

/// A connected peer.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Peer {
    pub uid: u32,
    pub gid: u32,
    pub pid: Option<i32>,
    /// User name, or the uid as text when it has none.
    pub user: String,
    pub role: Option<Role>,
}

/// How roles are granted.
#[derive(Clone, Debug, PartialEq)]
pub struct RolePolicy {
    pub operator_gid: Option<u32>,
    pub viewer_gid: Option<u32>,
    pub service_uid: u32,
    /// The group names, for messages.
    pub operator_group: String,
    pub viewer_group: String,
}

impl RolePolicy {
    /// Resolve the group names (a group that does not exist grants nothing).
    pub fn from_names(operator_group: &str, viewer_group: &str) -> Self {
        RolePolicy {
            operator_gid: group_gid(operator_group),
            viewer_gid: group_gid(viewer_group),
            operator_group: operator_group.to_string(),
            viewer_group: viewer_group.to_string(),
            // SAFETY: geteuid has no preconditions.
            service_uid: unsafe { libc::geteuid() },
        }
    }

    /// The role of a peer with `uid` and primary `gid`.
    pub fn role_of(&self, uid: u32, gid: u32) -> Option<Role> {
        if uid == 0 || uid == self.service_uid {
            return Some(Role::Operator);
        }
        let groups = user_name(uid)
            .map(|name| user_groups(&name, gid))
            .unwrap_or_else(|| vec![gid]);
        if self.operator_gid.is_some_and(|g| groups.contains(&g)) {
            Some(Role::Operator)
        } else if self.viewer_gid.is_some_and(|g| groups.contains(&g)) {
            Some(Role::Viewer)
        } else {
            None
        }
    }

    /// Describe a peer.
    pub fn peer(&self, uid: u32, gid: u32, pid: Option<i32>) -> Peer {
        Peer {
            uid,
            gid,
            pid,
            user: user_name(uid).unwrap_or_else(|| uid.to_string()),
            role: self.role_of(uid, gid),
        }
    }
}

/// The `system.posix_acl_access` value (linux/posix_acl_xattr.h: version 2, then tag, permission
/// and id per entry, little-endian, sorted by tag and id) that gives the owner and the groups
/// `gids` read and write, and the owning group and everyone else nothing.
pub fn acl_xattr(gids: &[u32]) -> Vec<u8> {
    const USER_OBJ: u16 = 0x01;
    const GROUP_OBJ: u16 = 0x04;
    const GROUP: u16 = 0x08;
    const MASK: u16 = 0x10;
    const OTHER: u16 = 0x20;
    const RW: u16 = 6;
    const NO_ID: u32 = u32::MAX;
    let mut gids = gids.to_vec();
    gids.sort_unstable();
    gids.dedup();
    let mut entries = vec![(USER_OBJ, RW, NO_ID), (GROUP_OBJ, 0, NO_ID)];
    entries.extend(gids.iter().map(|&g| (GROUP, RW, g)));
    entries.extend([(MASK, RW, NO_ID), (OTHER, 0, NO_ID)]);
    let mut out = 2u32.to_le_bytes().to_vec();
    for (tag, perm, id) in entries {
        out.extend(tag.to_le_bytes());
        out.extend(perm.to_le_bytes());
        out.extend(id.to_le_bytes());
    }
    out
}

/// Let only the owner and the groups `gids` connect to the socket at `path` (read and write),
/// with an access ACL. Fails with `Unsupported` on a file system without POSIX ACLs.
pub fn open_to_groups(path: &std::path::Path, gids: &[u32]) -> std::io::Result<()> {
    use std::os::unix::ffi::OsStrExt;
    let cpath = CString::new(path.as_os_str().as_bytes())
        .map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidInput, e))?;
    let value = acl_xattr(gids);
    // SAFETY: both strings are NUL-terminated and value's pointer and length match.
    let rc = unsafe {
        libc::setxattr(
            cpath.as_ptr(),
            c"system.posix_acl_access".as_ptr(),
            value.as_ptr().cast(),
            value.len(),
            0,
        )
    };
    if rc == 0 {
        return Ok(());
    }
    let e = std::io::Error::last_os_error();
    if e.raw_os_error() == Some(libc::EOPNOTSUPP) {
        return Err(std::io::Error::new(std::io::ErrorKind::Unsupported, e));
    }
    Err(e)
}

fn buffer_size(kind: libc::c_int) -> usize {
    // SAFETY: sysconf has no preconditions.
    let n = unsafe { libc::sysconf(kind) };
    if n > 0 { n as usize } else { 16 * 1024 }
}

/// The gid of a group name.
pub fn group_gid(name: &str) -> Option<u32> {
    let cname = CString::new(name).ok()?;
    let mut buf = vec![0u8; buffer_size(libc::_SC_GETGR_R_SIZE_MAX).max(1024)];
    for _ in 0..8 {
        // SAFETY: all pointers are valid for the duration of the call; buf's length is given.
        let mut grp: libc::group = unsafe { std::mem::zeroed() };
        let mut out: *mut libc::group = std::ptr::null_mut();
        let rc = unsafe {
            libc::getgrnam_r(
                cname.as_ptr(),
                &mut grp,
                buf.as_mut_ptr().cast(),
                buf.len(),
                &mut out,
            )
        };
        if rc == libc::ERANGE {
            buf.resize(buf.len() * 2, 0);
            continue;
        }
        return (rc == 0 && !out.is_null()).then_some(grp.gr_gid);
    }
    None
}

/// The user name of a uid.
pub fn user_name(uid: u32) -> Option<String> {
    let mut buf = vec![0u8; buffer_size(libc::_SC_GETPW_R_SIZE_MAX).max(1024)];
    for _ in 0..8 {
        // SAFETY: as for getgrnam_r.
        let mut pw: libc::passwd = unsafe { std::mem::zeroed() };
        let mut out: *mut libc::passwd = std::ptr::null_mut();
        let rc =
            unsafe { libc::getpwuid_r(uid, &mut pw, buf.as_mut_ptr().cast(), buf.len(), &mut out) };
        if rc == libc::ERANGE {
            buf.resize(buf.len() * 2, 0);
            continue;
        }
        if rc != 0 || out.is_null() || pw.pw_name.is_null() {
            return None;
        }
        // SAFETY: pw_name points into buf, NUL-terminated by the C library.
        let name = unsafe { CStr::from_ptr(pw.pw_name) };
        return Some(name.to_string_lossy().into_owned());
    }
    None
}

/// All groups of a user (primary and supplementary).
pub fn user_groups(name: &str, primary: u32) -> Vec<u32> {
    let Ok(cname) = CString::new(name) else {
        return vec![primary];
    };
    let mut n: libc::c_int = 32;
    for _ in 0..8 {
        let mut groups = vec![0 as libc::gid_t; n as usize];
        let mut count = n;
        // SAFETY: groups has room for `count` entries; count is updated by the call.
        let rc =
            unsafe { libc::getgrouplist(cname.as_ptr(), primary, groups.as_mut_ptr(), &mut count) };
        if rc >= 0 {
            groups.truncate(count.max(0) as usize);
            return groups;
        }
        n = count.max(n * 2);
    }
    vec![primary]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn root_and_self_are_operators_strangers_nothing() {
        let p = RolePolicy {
            operator_group: String::new(),
            viewer_group: String::new(),
            operator_gid: None,
            viewer_gid: None,
            service_uid: 4242,
        };
        assert_eq!(p.role_of(0, 0), Some(Role::Operator));
        assert_eq!(p.role_of(4242, 100), Some(Role::Operator));
        assert_eq!(p.role_of(65534, 65534), None);
    }

    #[test]
    fn group_membership_grants_roles() {
        // "nogroup"/"nobody" exist on Debian; gid of root's group is 0.
        let root_gid = group_gid("root").expect("group root exists");
        assert_eq!(root_gid, 0);
        assert_eq!(user_name(0).as_deref(), Some("root"));
        assert!(user_groups("root", 0).contains(&0));
        let p = RolePolicy {
            operator_group: String::new(),
            viewer_group: String::new(),
            operator_gid: None,
            viewer_gid: Some(65534),
            service_uid: 4242,
        };
        // A uid with no passwd entry: only its primary gid counts.
        assert_eq!(p.role_of(54321, 65534), Some(Role::Viewer));
        assert_eq!(p.role_of(54321, 1), None);
        assert_eq!(group_gid("no-such-group-axiscomp"), None);
    }

    #[test]
    fn the_socket_acl_is_the_kernel_format() {
        // Version 2; user::rw-, group::---, group:100:rw-, group:1001:rw-, mask::rw-,
        // other::--- (what `setfacl -m g:100:rw,g:1001:rw,g::-,o::-` stores).
        let want: Vec<u8> = [
            &[2, 0, 0, 0][..],
            &[1, 0, 6, 0, 0xff, 0xff, 0xff, 0xff],
            &[4, 0, 0, 0, 0xff, 0xff, 0xff, 0xff],
            &[8, 0, 6, 0, 100, 0, 0, 0],
            &[8, 0, 6, 0, 0xe9, 0x03, 0, 0],
            &[0x10, 0, 6, 0, 0xff, 0xff, 0xff, 0xff],
            &[0x20, 0, 0, 0, 0xff, 0xff, 0xff, 0xff],
        ]
        .concat();
        assert_eq!(acl_xattr(&[1001, 100, 1001]), want);
    }

    #[test]
    fn a_socket_open_to_groups_refuses_others() {
        use std::os::unix::fs::PermissionsExt;
        let dir = std::env::temp_dir().join(format!("axiscomp-acl-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("s.sock");
        let _ = std::fs::remove_file(&path);
        let _l = std::os::unix::net::UnixListener::bind(&path).unwrap();
        match open_to_groups(&path, &[65534]) {
            Ok(()) => {
                let mode = std::fs::metadata(&path).unwrap().permissions().mode() & 0o777;
                // Owner rw, the mask (shown as the group bits) rw, others nothing.
                assert_eq!(mode, 0o660, "{mode:o}");
            }
            Err(e) => assert_eq!(e.kind(), std::io::ErrorKind::Unsupported, "{e}"),
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
