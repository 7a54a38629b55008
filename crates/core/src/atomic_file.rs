//! Whole-or-nothing file writes, for every file moonhaul produces (policies, checkpoints,
//! logs, CSVs, plots): the content goes to a hidden temporary sibling, is synced to disk and
//! renamed over the target, so a reader — or a robot booting after a power cut — sees the
//! old file or the new one, never half of one. Files that belong together (a CSV and its
//! plot) are published as a [`Group`], so a reader never sees a new one beside an old one.
//!
//! # Rules every write follows
//!
//! - **Only regular files are replaced.** If anything else is at the target path — a
//!   directory, a symbolic link (it is refused, not followed), a FIFO, a socket, a device such
//!   as `/dev/null` — the write fails with [`io::ErrorKind::InvalidInput`] and a message naming
//!   the path, before the writer runs. (A rename would silently replace the device node or
//!   the link itself; a write through it would block or go elsewhere.) A missing target is
//!   created.
//! - **Permissions are kept.** The new file gets the permission bits (`0o777`; not the
//!   set-id or sticky bits) of the file it replaces; a new target gets the process's default
//!   (`0o666` less the umask). Ownership is not copied: the new file belongs to the writer.
//! - **No temporary outlives a failure.** The temporary is removed on every error path
//!   (a failing writer, sync, permission change or rename) and if the writer panics.
//! - **Temporaries are recognizable.** They are named `.tmp-<pid>-<n>-<file name>`: hidden,
//!   the writing process's id, a per-process counter, and the target's full file name (so its
//!   extension, from which writers such as image encoders choose the format).
//! - **Leftovers of killed writers are cleaned.** A process killed mid-write leaves its
//!   temporary behind. Each write of a target first removes every regular file named
//!   `.tmp-<pid>-<n>-<that same file name>` beside it whose `<pid>` is not this process and
//!   names no running process (`/proc/<pid>` absent). This is best effort and never fails the
//!   write; it is skipped where there is no `/proc` (then no process could be told alive).
//!   A writer in another PID namespace (another container sharing the folder) looks dead from
//!   here: its temporary may be removed under it, which fails *its* write (the old file stays
//!   intact) — never corrupts one.

use std::fs::{self, File, OpenOptions};
use std::io;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

/// The hidden prefix of every temporary: `.tmp-<pid>-<n>-<file name>`.
const TEMP_PREFIX: &str = ".tmp-";

/// Writes `path` by letting `write` fill a temporary sibling, then syncing it, giving it the
/// old file's permissions and renaming it into place (the rules are in the
/// [module docs](self)). `write` gets the path of an existing, empty file that it may
/// overwrite, truncate or recreate. `io_error` turns I/O failures into the caller's error
/// type; a refused target is one of them (kind [`io::ErrorKind::InvalidInput`]).
pub fn write_with<E>(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), E>,
    io_error: impl Fn(io::Error) -> E,
) -> Result<(), E> {
    let staged = Staged::new(path, write, &io_error)?;
    staged.rename_in().map_err(&io_error)
}

/// Writes `bytes` to `path` atomically (see [`write_with`]).
pub fn write(path: &Path, bytes: &[u8]) -> io::Result<()> {
    write_with(path, |temp| fs::write(temp, bytes), |e| e)
}

/// Writes a secret (a key file) atomically under the rules of the [module docs](self), except
/// for permissions: the file is private, exactly `0o600`, whatever the umask and whatever the
/// file it replaces had, and never readable by others, not even for a moment (the temporary
/// is created `0o600` and made exactly that before a byte is written). With `replace` false
/// an existing target is kept and the write fails with [`io::ErrorKind::AlreadyExists`] —
/// also when the target appears while the content is staged: the temporary is hard-linked
/// into place, which never replaces an entry (a filesystem without hard links falls back to
/// a rename after a last check). On unix only; elsewhere the permissions are the default.
pub fn write_private(path: &Path, bytes: &[u8], replace: bool) -> io::Result<()> {
    if !replace && check_target(path)?.is_some() {
        return Err(exists(path));
    }
    let staged = Staged::new_with(
        path,
        |temp| {
            let mut file = OpenOptions::new().write(true).open(temp)?;
            set_private(&file)?;
            io::Write::write_all(&mut file, bytes)
        },
        |e| e,
        Permissions::Private,
    )?;
    if replace {
        return staged.rename_in();
    }
    staged.link_in()
}

fn exists(path: &Path) -> io::Error {
    io::Error::new(
        io::ErrorKind::AlreadyExists,
        format!("{} exists", path.display()),
    )
}

/// Exactly `0o600` (the umask could only have removed bits).
fn set_private(file: &File) -> io::Result<()> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        file.set_permissions(fs::Permissions::from_mode(0o600))?;
    }
    #[cfg(not(unix))]
    let _ = file;
    Ok(())
}

/// The permissions a staged file gets.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Permissions {
    /// Those of the file it replaces (a new one: the process's default).
    KeepOld,
    /// Exactly `0o600`, from the temporary's creation on.
    Private,
}

/// Files that belong together (a CSV and its plot, two plots of one run), published so that a
/// reader never sees a new member beside an old one.
///
/// [`Group::stage`] writes each member to its temporary (the rules of the
/// [module docs](self) apply to each); [`Group::publish`] then removes every old target and
/// renames every temporary into place. A group dropped without being published — because a
/// `stage` failed and the caller returned early, say — removes its temporaries and leaves
/// every old file untouched.
///
/// **Guarantee:** at every moment, the members present are either all old (while the old ones
/// are being removed, some may already be absent) or all new (while the new ones are being
/// renamed in, some may not be there yet). A reader never sees a new file beside an old one;
/// a reader that finds a member missing is looking at a group being replaced. If `publish`
/// fails midway, the folder stays in one of those states and no temporary is left.
///
/// ```no_run
/// # fn main() -> std::io::Result<()> {
/// use moonhaul_core::atomic_file::Group;
/// use std::path::Path;
///
/// let mut group = Group::new(|_path: &Path, e| e);
/// group.stage(Path::new("out/demo.csv"), |temp| std::fs::write(temp, "t_s\n0.0\n"))?;
/// group.stage(Path::new("out/demo.png"), |temp| std::fs::write(temp, [0x89, b'P']))?;
/// group.publish()
/// # }
/// ```
#[must_use = "a group writes nothing until `publish` is called"]
pub struct Group<F> {
    /// Turns an I/O failure at a member's target path into the caller's error type.
    io_error: F,
    staged: Vec<Staged>,
}

impl<F, E> Group<F>
where
    F: Fn(&Path, io::Error) -> E,
{
    /// An empty group; `io_error` receives the target path an I/O failure concerns.
    pub fn new(io_error: F) -> Self {
        Self {
            io_error,
            staged: Vec::new(),
        }
    }

    /// Writes the member `path` to its temporary now (as [`write_with`] does before its
    /// rename). On error the member's temporary is removed; the caller drops the group to
    /// remove the others. A path staged twice (spelled the same way) is refused.
    pub fn stage(
        &mut self,
        path: &Path,
        write: impl FnOnce(&Path) -> Result<(), E>,
    ) -> Result<(), E> {
        if self.staged.iter().any(|s| s.target == path) {
            let e = io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("{} is staged twice in one group", path.display()),
            );
            return Err((self.io_error)(path, e));
        }
        let staged = Staged::new(path, write, |e| (self.io_error)(path, e))?;
        self.staged.push(staged);
        Ok(())
    }

    /// Checks every target is still a regular file or absent, removes every old target, then
    /// renames every temporary into place (the guarantee is in the [type docs](Group)).
    pub fn publish(self) -> Result<(), E> {
        let Self { io_error, staged } = self;
        for s in &staged {
            check_target(&s.target).map_err(|e| io_error(&s.target, e))?;
        }
        for s in &staged {
            if let Err(e) = fs::remove_file(&s.target) {
                if e.kind() != io::ErrorKind::NotFound {
                    return Err(io_error(&s.target, e));
                }
            }
        }
        // On an early return the remaining members drop, which removes their temporaries.
        for s in staged {
            let target = s.target.clone();
            s.rename_in().map_err(|e| io_error(&target, e))?;
        }
        Ok(())
    }
}

/// A target's content, written, synced and given its permissions, waiting in a temporary.
/// Dropping it removes the temporary, so every early return (and a panic) cleans up.
struct Staged {
    target: PathBuf,
    temp: PathBuf,
    /// False once the temporary has been renamed in (nothing left to remove).
    armed: bool,
}

impl Staged {
    fn new<E>(
        target: &Path,
        write: impl FnOnce(&Path) -> Result<(), E>,
        io_error: impl Fn(io::Error) -> E,
    ) -> Result<Self, E> {
        Self::new_with(target, write, io_error, Permissions::KeepOld)
    }

    fn new_with<E>(
        target: &Path,
        write: impl FnOnce(&Path) -> Result<(), E>,
        io_error: impl Fn(io::Error) -> E,
        permissions: Permissions,
    ) -> Result<Self, E> {
        let old = check_target(target).map_err(&io_error)?;
        let old = old.filter(|_| permissions == Permissions::KeepOld);
        remove_leftovers(target);
        let staged = Self {
            target: target.to_path_buf(),
            temp: create_temporary(target, permissions).map_err(&io_error)?,
            armed: true,
        };
        write(&staged.temp)?;
        // Sync first: a file the old permissions make unreadable could not be opened after.
        File::open(&staged.temp)
            .and_then(|file| file.sync_all())
            .and_then(|()| match &old {
                Some(metadata) => fs::set_permissions(&staged.temp, kept_permissions(metadata)),
                None => Ok(()),
            })
            .map_err(&io_error)?;
        Ok(staged)
    }

    /// Renames the temporary over the target, after checking once more (the writer may have
    /// taken a while) that the target is still a regular file or absent.
    fn rename_in(mut self) -> io::Result<()> {
        check_target(&self.target)?;
        fs::rename(&self.temp, &self.target)?;
        self.armed = false;
        Ok(())
    }

    /// Links the temporary in as the target, never replacing an entry there
    /// ([`io::ErrorKind::AlreadyExists`]); the temporary is removed either way.
    fn link_in(self) -> io::Result<()> {
        match fs::hard_link(&self.temp, &self.target) {
            Ok(()) => Ok(()),
            Err(e) if e.kind() == io::ErrorKind::AlreadyExists => Err(exists(&self.target)),
            // No hard links here: rename after a last check (a file appearing in between is
            // the one race left on such filesystems).
            Err(_) => match check_target(&self.target)? {
                Some(_) => Err(exists(&self.target)),
                None => self.rename_in(),
            },
        }
        // Dropping `self` (still armed after a link) removes the temporary's second name.
    }
}

impl Drop for Staged {
    fn drop(&mut self) {
        if self.armed {
            // Best effort: the first error is the one to report.
            let _ = fs::remove_file(&self.temp);
        }
    }
}

/// The metadata of the regular file at `path`, `None` if nothing is there, or an
/// [`io::ErrorKind::InvalidInput`] error naming the path if something else is (a symlink is
/// not followed).
fn check_target(path: &Path) -> io::Result<Option<fs::Metadata>> {
    match fs::symlink_metadata(path) {
        Ok(metadata) if metadata.file_type().is_file() => Ok(Some(metadata)),
        Ok(metadata) => Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            format!(
                "refusing to replace {}: it is {}, not a regular file",
                path.display(),
                describe(metadata.file_type())
            ),
        )),
        Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(e),
    }
}

fn describe(file_type: fs::FileType) -> &'static str {
    if file_type.is_dir() {
        return "a directory";
    }
    if file_type.is_symlink() {
        return "a symbolic link";
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if file_type.is_fifo() {
            return "a FIFO";
        }
        if file_type.is_socket() {
            return "a socket";
        }
        if file_type.is_char_device() {
            return "a character device";
        }
        if file_type.is_block_device() {
            return "a block device";
        }
    }
    "a special file"
}

/// The permissions the new file takes over from the old one.
#[cfg(unix)]
fn kept_permissions(old: &fs::Metadata) -> fs::Permissions {
    use std::os::unix::fs::PermissionsExt;
    fs::Permissions::from_mode(old.permissions().mode() & 0o777)
}

#[cfg(not(unix))]
fn kept_permissions(old: &fs::Metadata) -> fs::Permissions {
    old.permissions()
}

/// Creates a new, empty temporary sibling of `path` (never opening an existing entry, so a
/// planted symlink is not followed) and returns its path.
fn create_temporary(path: &Path, permissions: Permissions) -> io::Result<PathBuf> {
    /// Distinguishes concurrent writers within one process.
    static NEXT: AtomicUsize = AtomicUsize::new(0);
    let name = file_name(path)?;
    let mut attempts = 0;
    loop {
        let temp = path.with_file_name(format!(
            "{TEMP_PREFIX}{}-{}-{name}",
            std::process::id(),
            NEXT.fetch_add(1, Ordering::Relaxed),
        ));
        let mut options = OpenOptions::new();
        options.write(true).create_new(true);
        #[cfg(unix)]
        if permissions == Permissions::Private {
            use std::os::unix::fs::OpenOptionsExt;
            options.mode(0o600);
        }
        #[cfg(not(unix))]
        let _ = permissions;
        match options.open(&temp) {
            Ok(_) => return Ok(temp),
            // A leftover of an earlier process that had our pid: take the next number.
            Err(e) if e.kind() == io::ErrorKind::AlreadyExists && attempts < 16 => attempts += 1,
            Err(e) => return Err(e),
        }
    }
}

fn file_name(path: &Path) -> io::Result<String> {
    path.file_name()
        .map(|name| name.to_string_lossy().into_owned())
        .ok_or_else(|| {
            io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("{} has no file name", path.display()),
            )
        })
}

/// Removes the temporaries of `path` that dead processes left (rules in the
/// [module docs](self)). Best effort: every failure is ignored.
fn remove_leftovers(path: &Path) {
    let proc = Path::new("/proc");
    if !proc.join("self").exists() {
        return;
    }
    let Ok(name) = file_name(path) else { return };
    let dir = match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir,
        _ => Path::new("."),
    };
    let Ok(entries) = fs::read_dir(dir) else {
        return;
    };
    let own = std::process::id();
    for entry in entries.flatten() {
        let entry_name = entry.file_name();
        let Some(pid) = leftover_pid(&entry_name.to_string_lossy(), &name) else {
            continue;
        };
        let is_file = entry.file_type().is_ok_and(|t| t.is_file());
        if is_file && pid != own && !proc.join(pid.to_string()).exists() {
            let _ = fs::remove_file(entry.path());
        }
    }
}

/// The pid in `entry`, if `entry` is named like a temporary of the file `target_name`.
fn leftover_pid(entry: &str, target_name: &str) -> Option<u32> {
    let rest = entry.strip_prefix(TEMP_PREFIX)?;
    let (pid, rest) = rest.split_once('-')?;
    let (counter, name) = rest.split_once('-')?;
    let digits = |s: &str| !s.is_empty() && s.bytes().all(|b| b.is_ascii_digit());
    if name != target_name || !digits(pid) || !digits(counter) {
        return None;
    }
    pid.parse().ok()
}

#[cfg(test)]
mod tests {
    use super::*;
    #[cfg(unix)]
    use std::os::unix::fs::PermissionsExt;

    fn entries(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    }

    fn assert_refused(err: &io::Error, path: &Path, what: &str) {
        assert_eq!(err.kind(), io::ErrorKind::InvalidInput, "{err}");
        let message = err.to_string();
        assert!(message.contains(&path.display().to_string()), "{message}");
        assert!(message.contains(what), "{message}");
    }

    #[test]
    fn replaces_whole_and_leaves_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        let dir = dir.path();
        let target = dir.join("policy.safetensors");
        write(&target, b"old").unwrap();
        write(&target, b"new").unwrap();
        assert_eq!(fs::read(&target).unwrap(), b"new");
        assert_eq!(entries(dir), ["policy.safetensors"]);

        // A failing writer leaves the old content and no temporary behind.
        let failed = write_with(
            &target,
            |temp| {
                assert!(temp.to_string_lossy().ends_with("policy.safetensors"));
                fs::write(temp, b"half")?;
                Err(io::Error::other("encoder failed"))
            },
            |e| e,
        );
        assert_eq!(failed.unwrap_err().to_string(), "encoder failed");
        assert_eq!(fs::read(&target).unwrap(), b"new");
        assert_eq!(entries(dir), ["policy.safetensors"]);

        // So does a failing sync (here: the writer removed its temporary).
        let failed = write_with(&target, |t| fs::remove_file(t), |e| e).unwrap_err();
        assert_eq!(failed.kind(), io::ErrorKind::NotFound);
        assert_eq!(entries(dir), ["policy.safetensors"]);

        let missing_dir = write(&dir.join("absent").join("x.csv"), b"x").unwrap_err();
        assert_eq!(missing_dir.kind(), io::ErrorKind::NotFound);
    }

    #[cfg(unix)]
    #[test]
    fn private_writes_are_0600_and_replace_only_when_asked() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("team.keys.toml");
        let mode = |p: &Path| fs::metadata(p).unwrap().permissions().mode() & 0o777;
        write_private(&target, b"secret 1", false).unwrap();
        assert_eq!(mode(&target), 0o600);
        let kept = write_private(&target, b"secret 2", false).unwrap_err();
        assert_eq!(kept.kind(), io::ErrorKind::AlreadyExists, "{kept}");
        assert_eq!(fs::read(&target).unwrap(), b"secret 1");
        // A replaced file's looser mode is not kept: a secret stays private.
        fs::set_permissions(&target, fs::Permissions::from_mode(0o644)).unwrap();
        write_private(&target, b"secret 3", true).unwrap();
        assert_eq!(fs::read(&target).unwrap(), b"secret 3");
        assert_eq!(mode(&target), 0o600);
        assert_eq!(entries(dir.path()), ["team.keys.toml"]);
        let sub = dir.path().join("sub");
        fs::create_dir(&sub).unwrap();
        let refused = write_private(&sub, b"x", true).unwrap_err();
        assert_refused(&refused, &sub, "a directory");
    }

    #[test]
    fn panicking_writer_leaves_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("a.csv");
        let panicked = std::panic::catch_unwind(|| {
            write_with(
                &target,
                |_| -> io::Result<()> { panic!("writer bug") },
                |e| e,
            )
        });
        assert!(panicked.is_err());
        assert!(entries(dir.path()).is_empty());
    }

    #[cfg(unix)]
    #[test]
    fn refuses_fifo_without_blocking() {
        use std::os::unix::fs::FileTypeExt;
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("demo.csv");
        let status = std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap();
        assert!(status.success());
        let err = write(&fifo, b"x").unwrap_err();
        assert_refused(&err, &fifo, "FIFO");
        assert!(fs::symlink_metadata(&fifo).unwrap().file_type().is_fifo());
        assert_eq!(entries(dir.path()), ["demo.csv"]);
    }

    #[cfg(unix)]
    #[test]
    fn refuses_symlink_without_following_it() {
        let dir = tempfile::tempdir().unwrap();
        let real = dir.path().join("real.csv");
        fs::write(&real, b"precious").unwrap();
        let link = dir.path().join("demo.csv");
        std::os::unix::fs::symlink(&real, &link).unwrap();
        let err = write(&link, b"x").unwrap_err();
        assert_refused(&err, &link, "symbolic link");
        assert_eq!(fs::read(&real).unwrap(), b"precious");
        assert!(fs::symlink_metadata(&link)
            .unwrap()
            .file_type()
            .is_symlink());
        // A dangling link is refused too, not created through.
        let dangling = dir.path().join("dangling.csv");
        std::os::unix::fs::symlink(dir.path().join("nowhere"), &dangling).unwrap();
        assert_refused(
            &write(&dangling, b"x").unwrap_err(),
            &dangling,
            "symbolic link",
        );
        assert_eq!(
            entries(dir.path()),
            ["dangling.csv", "demo.csv", "real.csv"]
        );
    }

    #[test]
    fn refuses_directory() {
        let dir = tempfile::tempdir().unwrap();
        let sub = dir.path().join("demo.png");
        fs::create_dir(&sub).unwrap();
        fs::write(sub.join("inside"), b"kept").unwrap();
        let mut ran = false;
        let err = write_with(
            &sub,
            |_| {
                ran = true;
                Ok(())
            },
            |e| e,
        )
        .unwrap_err();
        assert_refused(&err, &sub, "directory");
        assert!(!ran, "the writer ran for a refused target");
        assert_eq!(entries(dir.path()), ["demo.png"]);
        assert_eq!(fs::read(sub.join("inside")).unwrap(), b"kept");
    }

    #[cfg(unix)]
    #[test]
    fn refuses_device() {
        let null = Path::new("/dev/null");
        assert_refused(&write(null, b"x").unwrap_err(), null, "character device");
        assert!(!fs::symlink_metadata(null).unwrap().file_type().is_file());
    }

    #[cfg(unix)]
    #[test]
    fn keeps_permissions_of_the_replaced_file() {
        let dir = tempfile::tempdir().unwrap();
        let mode = |p: &Path| fs::metadata(p).unwrap().permissions().mode() & 0o7777;
        for wanted in [0o600, 0o640, 0o444] {
            let target = dir.path().join(format!("f{wanted:o}"));
            fs::write(&target, b"old").unwrap();
            fs::set_permissions(&target, fs::Permissions::from_mode(wanted)).unwrap();
            write(&target, b"new").unwrap();
            assert_eq!(fs::read(&target).unwrap(), b"new");
            assert_eq!(mode(&target), wanted, "{}", target.display());
        }
        assert_eq!(entries(dir.path()).len(), 3, "temporary left behind");
    }

    /// The id of a process that has exited (and been reaped).
    fn dead_pid() -> u32 {
        let mut child = std::process::Command::new("true").spawn().unwrap();
        let pid = child.id();
        child.wait().unwrap();
        pid
    }

    #[test]
    fn cleans_leftovers_of_dead_writers_of_the_same_target() {
        if !Path::new("/proc/self").exists() {
            return; // No way to tell a process alive; cleaning is skipped by design.
        }
        let dir = tempfile::tempdir().unwrap();
        let dead = dead_pid();
        let own = std::process::id();
        let names = [
            format!(".tmp-{dead}-3-demo.csv"), // dead writer, same target: removed
            format!(".tmp-{dead}-0-demo.csv.bak"), // another target: kept
            format!(".tmp-{dead}-0-other.csv"), // another target: kept
            format!(".tmp-{own}-999-demo.csv"), // this process (maybe another thread): kept
            ".tmp-1-0-demo.csv".to_owned(),    // a live process: kept
            format!(".tmp-{dead}-x-demo.csv"), // not a temporary's name: kept
        ];
        for name in &names {
            fs::write(dir.path().join(name), b"leftover").unwrap();
        }
        write(&dir.path().join("demo.csv"), b"new").unwrap();
        let mut expected: Vec<String> = names[1..].to_vec();
        expected.push("demo.csv".into());
        expected.sort();
        assert_eq!(entries(dir.path()), expected);
    }

    #[test]
    fn leftover_names_parse() {
        assert_eq!(leftover_pid(".tmp-12-0-a.csv", "a.csv"), Some(12));
        assert_eq!(leftover_pid(".tmp-12-0-a-b.csv", "a-b.csv"), Some(12));
        for other in [
            ".tmp-12-0-b.csv",
            ".tmp--0-a.csv",
            ".tmp-12--a.csv",
            "a.csv",
        ] {
            assert_eq!(leftover_pid(other, "a.csv"), None, "{other}");
        }
    }

    type IoGroup = Group<fn(&Path, io::Error) -> io::Error>;

    fn io_group() -> IoGroup {
        Group::new(|path, e| io::Error::new(e.kind(), format!("{}: {e}", path.display())))
    }

    #[test]
    fn group_publishes_all_members() {
        let dir = tempfile::tempdir().unwrap();
        let (csv, png) = (dir.path().join("demo.csv"), dir.path().join("demo.png"));
        fs::write(&csv, b"old csv").unwrap();
        let mut group = io_group();
        group.stage(&csv, |t| fs::write(t, b"new csv")).unwrap();
        group.stage(&png, |t| fs::write(t, b"new png")).unwrap();
        // Staged, not yet published: the old file is still in place.
        assert_eq!(fs::read(&csv).unwrap(), b"old csv");
        assert!(!png.exists());
        group.publish().unwrap();
        assert_eq!(fs::read(&csv).unwrap(), b"new csv");
        assert_eq!(fs::read(&png).unwrap(), b"new png");
        assert_eq!(entries(dir.path()), ["demo.csv", "demo.png"]);
    }

    #[test]
    fn failed_group_leaves_old_files_and_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        let (csv, png) = (dir.path().join("demo.csv"), dir.path().join("demo.png"));
        fs::write(&csv, b"old csv").unwrap();
        fs::write(&png, b"old png").unwrap();
        let attempt = || -> io::Result<()> {
            let mut group = io_group();
            group.stage(&csv, |t| fs::write(t, b"new csv"))?;
            group.stage(&png, |t| {
                fs::write(t, b"half a png")?;
                Err(io::Error::other("encoder failed"))
            })?;
            group.publish()
        };
        assert_eq!(attempt().unwrap_err().to_string(), "encoder failed");
        assert_eq!(fs::read(&csv).unwrap(), b"old csv");
        assert_eq!(fs::read(&png).unwrap(), b"old png");
        assert_eq!(entries(dir.path()), ["demo.csv", "demo.png"]);

        // A group never published writes nothing either.
        let mut group = io_group();
        group.stage(&csv, |t| fs::write(t, b"new csv")).unwrap();
        drop(group);
        assert_eq!(fs::read(&csv).unwrap(), b"old csv");
        assert_eq!(entries(dir.path()), ["demo.csv", "demo.png"]);
    }

    #[test]
    fn group_refuses_bad_members_before_touching_old_files() {
        let dir = tempfile::tempdir().unwrap();
        let (csv, png) = (dir.path().join("demo.csv"), dir.path().join("demo.png"));
        fs::write(&csv, b"old csv").unwrap();
        fs::create_dir(&png).unwrap();
        let mut group = io_group();
        group.stage(&csv, |t| fs::write(t, b"new csv")).unwrap();
        let err = group.stage(&png, |t| fs::write(t, b"new png")).unwrap_err();
        assert_refused(&err, &png, "directory");
        let twice = group.stage(&csv, |t| fs::write(t, b"x")).unwrap_err();
        assert_eq!(twice.kind(), io::ErrorKind::InvalidInput);
        assert!(twice.to_string().contains("staged twice"), "{twice}");
        drop(group);
        assert_eq!(fs::read(&csv).unwrap(), b"old csv");
        assert_eq!(entries(dir.path()), ["demo.csv", "demo.png"]);

        // A target replaced by a directory between staging and publishing: nothing changes.
        fs::remove_dir(&png).unwrap();
        let mut group = io_group();
        group.stage(&csv, |t| fs::write(t, b"new csv")).unwrap();
        group.stage(&png, |t| fs::write(t, b"new png")).unwrap();
        fs::create_dir(&png).unwrap();
        assert_refused(&group.publish().unwrap_err(), &png, "directory");
        assert_eq!(fs::read(&csv).unwrap(), b"old csv");
        assert_eq!(entries(dir.path()), ["demo.csv", "demo.png"]);
    }
}
