//! Who is on the other end of the control socket (peer credentials, SO_PEERCRED) and what they
//! may do: viewing needs the viewer group, changing anything the operator group (DESIGN §8).
//! Root and the service's own user are operators. Group membership includes supplementary
//! groups, looked up through the C library (so NSS users and groups work).
//!
//! A directory behind NSS (LDAP, sssd) may take seconds to answer, and the service has one
//! event loop: a connection's lookups run on a blocking thread ([`Directory`]), and their
//! answers are kept by uid and gid for [`LOOKUP_TTL`], so a changed group membership is seen
//! within a minute.
//!
//! The socket file itself admits only the two groups (and its owner): a POSIX access ACL
//! ([`open_to_groups`]), since one file has one group and a site's viewers and operators are
//! two. Everyone else is refused by the kernel on connect.

use super::api::Role;
use nix::unistd::{Gid, Group, Uid, User};
use serde::Serialize;
use std::collections::HashMap;
use std::ffi::CString;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// How long the directory's answer about a peer is kept.
pub const LOOKUP_TTL: Duration = Duration::from_secs(60);

/// The answers kept at most (the oldest goes first).
pub const LOOKUP_CAPACITY: usize = 64;

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
#[derive(Clone, Debug)]
pub struct RolePolicy {
    pub operator_gid: Option<u32>,
    pub viewer_gid: Option<u32>,
    pub service_uid: u32,
    /// The group names, for messages.
    pub operator_group: String,
    pub viewer_group: String,
    /// Where the peers' names and groups come from (shared by every clone).
    pub directory: Directory,
}

impl RolePolicy {
    /// Resolve the group names (a group that does not exist grants nothing).
    pub fn from_names(operator_group: &str, viewer_group: &str) -> Self {
        RolePolicy {
            operator_gid: group_gid(operator_group),
            viewer_gid: group_gid(viewer_group),
            operator_group: operator_group.to_string(),
            viewer_group: viewer_group.to_string(),
            service_uid: nix::unistd::geteuid().as_raw(),
            directory: Directory::new(),
        }
    }

    /// The role of a peer with `uid` whose groups the directory gives in `account`.
    pub fn role_of(&self, uid: u32, account: &Account) -> Option<Role> {
        if uid == 0 || uid == self.service_uid {
            return Some(Role::Operator);
        }
        let groups = &account.groups;
        if self.operator_gid.is_some_and(|g| groups.contains(&g)) {
            Some(Role::Operator)
        } else if self.viewer_gid.is_some_and(|g| groups.contains(&g)) {
            Some(Role::Viewer)
        } else {
            None
        }
    }

    /// Describe a peer, from the directory's answer (kept, or looked up off the event loop).
    pub async fn peer(&self, uid: u32, gid: u32, pid: Option<i32>) -> Peer {
        let account = self.directory.account(uid, gid).await;
        Peer {
            uid,
            gid,
            pid,
            role: self.role_of(uid, &account),
            user: account.user.unwrap_or_else(|| uid.to_string()),
        }
    }
}

/// What the directory says of a peer.
#[derive(Clone, Debug, PartialEq)]
pub struct Account {
    /// The user name; `None` for a uid with no passwd entry.
    pub user: Option<String>,
    /// Its groups, primary and supplementary (the primary alone without a passwd entry).
    pub groups: Vec<u32>,
}

impl Account {
    /// Ask the directory about `uid` with primary group `gid`. Blocks for as long as NSS takes:
    /// never on the event loop ([`Directory::account`]).
    pub fn look_up(uid: u32, gid: u32) -> Account {
        let user = user_name(uid);
        let groups = user
            .as_deref()
            .map(|name| user_groups(name, gid))
            .unwrap_or_else(|| vec![gid]);
        Account { user, groups }
    }
}

/// The directory's answers by (uid, gid), each kept for [`LOOKUP_TTL`], at most
/// [`LOOKUP_CAPACITY`] of them (sans-I/O: the time is an argument).
#[derive(Debug, Default)]
struct Cache {
    entries: HashMap<(u32, u32), (Instant, Account)>,
}

impl Cache {
    /// The answer for `key`, when one younger than [`LOOKUP_TTL`] is kept.
    fn get(&self, key: (u32, u32), now: Instant) -> Option<&Account> {
        self.entries
            .get(&key)
            .filter(|(at, _)| now.saturating_duration_since(*at) < LOOKUP_TTL)
            .map(|(_, a)| a)
    }

    /// Keep `account` as the answer for `key` given at `at`; expired answers go, and the
    /// oldest when the cache is full.
    fn insert(&mut self, key: (u32, u32), account: Account, at: Instant) {
        self.entries
            .retain(|_, (t, _)| at.saturating_duration_since(*t) < LOOKUP_TTL);
        if self.entries.len() >= LOOKUP_CAPACITY && !self.entries.contains_key(&key) {
            let oldest = self
                .entries
                .iter()
                .min_by_key(|(_, (t, _))| *t)
                .map(|(k, _)| *k);
            if let Some(k) = oldest {
                self.entries.remove(&k);
            }
        }
        self.entries.insert(key, (at, account));
    }
}

/// The user directory as the control socket asks it: a miss is looked up on a blocking thread
/// (a slow NSS or LDAP server holds that thread, not the service's event loop) and kept
/// ([`LOOKUP_TTL`], [`LOOKUP_CAPACITY`]). Clones share the answers.
#[derive(Clone, Debug)]
pub struct Directory {
    cache: Arc<Mutex<Cache>>,
    look_up: fn(u32, u32) -> Account,
}

impl Default for Directory {
    fn default() -> Self {
        Directory::new()
    }
}

impl Directory {
    /// The system's directory, through the C library.
    pub fn new() -> Self {
        Directory::with_lookup(Account::look_up)
    }

    /// A directory that asks `look_up` (a test's stand-in for NSS).
    pub fn with_lookup(look_up: fn(u32, u32) -> Account) -> Self {
        Directory {
            cache: Arc::default(),
            look_up,
        }
    }

    /// What the directory says of `uid` with primary group `gid`: the kept answer, else a
    /// lookup off the event loop (a lookup that panicked counts as no passwd entry, unkept).
    pub async fn account(&self, uid: u32, gid: u32) -> Account {
        let now = crate::util::clock::now();
        if let Some(a) = self.cache().get((uid, gid), now) {
            return a.clone();
        }
        let look_up = self.look_up;
        match tokio::task::spawn_blocking(move || look_up(uid, gid)).await {
            Ok(account) => {
                self.cache().insert((uid, gid), account.clone(), now);
                account
            }
            Err(e) => {
                tracing::warn!("control: looking up uid {uid} failed: {e}");
                Account {
                    user: None,
                    groups: vec![gid],
                }
            }
        }
    }

    fn cache(&self) -> std::sync::MutexGuard<'_, Cache> {
        self.cache.lock().unwrap_or_else(|p| p.into_inner())
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

/// The gid of a group name. Blocks on NSS.
pub fn group_gid(name: &str) -> Option<u32> {
    Group::from_name(name)
        .ok()
        .flatten()
        .map(|g| g.gid.as_raw())
}

/// The user name of a uid. Blocks on NSS.
pub fn user_name(uid: u32) -> Option<String> {
    User::from_uid(Uid::from_raw(uid))
        .ok()
        .flatten()
        .map(|u| u.name)
        .filter(|n| !n.is_empty())
}

/// All groups of a user (primary and supplementary). Blocks on NSS.
pub fn user_groups(name: &str, primary: u32) -> Vec<u32> {
    let groups = CString::new(name)
        .ok()
        .and_then(|n| nix::unistd::getgrouplist(&n, Gid::from_raw(primary)).ok());
    match groups {
        Some(g) => g.into_iter().map(Gid::as_raw).collect(),
        None => vec![primary],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn policy(
        operator_gid: Option<u32>,
        viewer_gid: Option<u32>,
        directory: Directory,
    ) -> RolePolicy {
        RolePolicy {
            operator_group: String::new(),
            viewer_group: String::new(),
            operator_gid,
            viewer_gid,
            service_uid: 4242,
            directory,
        }
    }

    #[test]
    fn root_and_self_are_operators_strangers_nothing() {
        let p = policy(None, None, Directory::new());
        let groups = |g: u32| Account {
            user: None,
            groups: vec![g],
        };
        assert_eq!(p.role_of(0, &groups(0)), Some(Role::Operator));
        assert_eq!(p.role_of(4242, &groups(100)), Some(Role::Operator));
        assert_eq!(p.role_of(65534, &groups(65534)), None);
    }

    #[test]
    fn group_membership_grants_roles() {
        // "nogroup"/"nobody" exist on Debian; gid of root's group is 0.
        let root_gid = group_gid("root").expect("group root exists");
        assert_eq!(root_gid, 0);
        assert_eq!(user_name(0).as_deref(), Some("root"));
        assert!(user_groups("root", 0).contains(&0));
        let p = policy(None, Some(65534), Directory::new());
        // A uid with no passwd entry: only its primary gid counts.
        let stranger = |gid| p.role_of(54321, &Account::look_up(54321, gid));
        assert_eq!(stranger(65534), Some(Role::Viewer));
        assert_eq!(stranger(1), None);
        assert_eq!(group_gid("no-such-group-axiscomp"), None);
    }

    /// The stand-in directory of `a_directory_answer_is_kept_for_a_minute`: user "ann" in
    /// `GROUPS`, counting the lookups.
    static LOOKUPS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    static GROUPS: Mutex<Vec<u32>> = Mutex::new(Vec::new());

    fn ann(_uid: u32, gid: u32) -> Account {
        LOOKUPS.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        let mut groups = vec![gid];
        groups.extend(GROUPS.lock().unwrap().iter());
        Account {
            user: Some("ann".into()),
            groups,
        }
    }

    /// A peer's lookup is kept for LOOKUP_TTL by uid and gid, then asked again: a group
    /// membership added meanwhile grants its role within the minute (simulated clock).
    #[tokio::test(start_paused = true)]
    async fn a_directory_answer_is_kept_for_a_minute() {
        use std::sync::atomic::Ordering::SeqCst;
        let lookups = || LOOKUPS.load(SeqCst);
        let p = policy(None, Some(7), Directory::with_lookup(ann));
        let peer = p.peer(1000, 100, Some(1)).await;
        assert_eq!((peer.user.as_str(), peer.role), ("ann", None));
        assert_eq!(lookups(), 1);
        // Ann joins the viewers; the answer kept still says she is not one.
        GROUPS.lock().unwrap().push(7);
        tokio::time::sleep(Duration::from_secs(30)).await;
        let clone = p.clone();
        assert_eq!(clone.peer(1000, 100, Some(2)).await.role, None);
        assert_eq!(lookups(), 1, "a hit, also from a clone");
        // Another primary group is another question.
        assert_eq!(p.peer(1000, 101, None).await.role, Some(Role::Viewer));
        assert_eq!(lookups(), 2);
        // A minute after the first lookup it has expired: asked again, she is a viewer.
        tokio::time::sleep(Duration::from_secs(30)).await;
        assert_eq!(p.peer(1000, 100, None).await.role, Some(Role::Viewer));
        assert_eq!(lookups(), 3);
        assert_eq!(p.peer(1000, 100, None).await.role, Some(Role::Viewer));
        assert_eq!(lookups(), 3);
    }

    /// The cache holds LOOKUP_CAPACITY answers: the oldest goes first, expired ones at once.
    #[test]
    fn the_cache_is_bounded() {
        let t0 = Instant::now();
        let at = |ms: u64| t0 + Duration::from_millis(ms);
        let account = |uid| Account {
            user: None,
            groups: vec![uid],
        };
        let mut c = Cache::default();
        for uid in 0..LOOKUP_CAPACITY as u32 + 5 {
            c.insert((uid, 0), account(uid), at(u64::from(uid)));
        }
        assert_eq!(c.entries.len(), LOOKUP_CAPACITY);
        let now = at(10_000);
        assert!((0..5).all(|uid| c.get((uid, 0), now).is_none()));
        assert_eq!(c.get((5, 0), now), Some(&account(5)));
        // Replacing an answer kept takes no room from another.
        c.insert((5, 0), account(55), now);
        assert_eq!(c.entries.len(), LOOKUP_CAPACITY);
        assert_eq!(c.get((5, 0), now), Some(&account(55)));
        // A minute on, all but the newest have expired and go with the next insert.
        let later = now + LOOKUP_TTL - Duration::from_secs(1);
        assert!(c.get((6, 0), later).is_none());
        c.insert((1000, 0), account(1000), later);
        assert_eq!(c.entries.len(), 2);
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
