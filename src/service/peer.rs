//! Who is on the other end of the control socket (peer credentials, SO_PEERCRED) and what they
//! may do: viewing needs the viewer group, changing anything the operator group (DESIGN §8).
//! Root and the service's own user are operators. Group membership includes supplementary
//! groups, looked up through the C library (so NSS users and groups work).

use serde::Serialize;
use std::ffi::{CStr, CString};

/// What a peer may do.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    Viewer,
    Operator,
}

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
}

impl RolePolicy {
    /// Resolve the group names (a group that does not exist grants nothing).
    pub fn from_names(operator_group: &str, viewer_group: &str) -> Self {
        RolePolicy {
            operator_gid: group_gid(operator_group),
            viewer_gid: group_gid(viewer_group),
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
            operator_gid: None,
            viewer_gid: Some(65534),
            service_uid: 4242,
        };
        // A uid with no passwd entry: only its primary gid counts.
        assert_eq!(p.role_of(54321, 65534), Some(Role::Viewer));
        assert_eq!(p.role_of(54321, 1), None);
        assert_eq!(group_gid("no-such-group-axiscomp"), None);
    }
}
