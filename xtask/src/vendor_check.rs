//! `cargo xtask vendor-check`: every crate under `vendor/` is its crates.io release plus its
//! `moonhaul.patch`, nothing else.
//!
//! For each `vendor/<dir>/` the name and version come from its own `Cargo.toml` (`[package]`).
//! The release's `.crate` (a gzip tarball) is downloaded once from static.crates.io into
//! `$CARGO_HOME/registry/cache/moonhaul-vendor-check/` (cargo never fetches a crate it patches,
//! so cargo's own cache does not have it) and checked against the SHA-256 pinned in
//! [`CHECKSUMS`]; a second run needs no network. The release is unpacked with `tar` into a
//! temporary directory, `moonhaul.patch` applied with `git apply`, and then compared byte for
//! byte with the vendored copy:
//!
//! - every file under `src/`, both ways (a file on one side only is a difference);
//! - `Cargo.toml`, against the release's with its `[[test]]`, `[[example]]` and `[[bench]]`
//!   sections removed (the vendored copy drops those targets; everything else, `[package]`,
//!   features and dependencies included, must be as released);
//! - `README.md` and `.cargo_vcs_info.json`, as released;
//! - no other file: besides those only moonhaul's `PATCHED.md` and `moonhaul.patch`, and cargo's
//!   `.cargo-ok` marker (not in the tarball, not compared) may be there. `PATCHED.md` is ours
//!   and not compared with anything.
//!
//! The download shells out to `python3` (its `urllib`): the standard library has no HTTPS
//! client, `python3` is on every machine this project runs on (CI included; `cargo xtask setup`
//! needs it anyway) while `curl` is not, and one code path is easier to trust than a fallback.
//! Hashing is the `sha2` crate's (the workspace's own, as the key files use), so an offline
//! run needs only `tar` and `git`.

use std::collections::BTreeSet;
use std::env;
use std::fs;
use std::path::{Path, PathBuf};
use std::process::Command;

use crate::{run, stage, workspace_root};
use sha2::{Digest as _, Sha256};

/// The SHA-256 of each vendored release's `.crate`, as crates.io publishes it: the `cksum`
/// field of that version's line in the sparse index (`https://index.crates.io/ra/pi/rapier3d`,
/// `https://index.crates.io/pa/rr/parry3d`), read 2026-12 and matching the downloaded files.
/// An upgrade adds the new version's line here (the check names the index URL when one is
/// missing); the version itself is read from the vendored manifest.
const CHECKSUMS: [(&str, &str, &str); 2] = [
    (
        "rapier3d",
        "0.36.1",
        "033e2edc815d61ab97bd74ed5d1cbea5ebe575218774a7cfedbd3551f0033317",
    ),
    (
        "parry3d",
        "0.31.1",
        "7b626edc0b497dba4bdf6e1e0797895294ed9f61dac2bd28cb5d34d37ad2ca7e",
    ),
];

/// Files a vendored crate may have at its top level besides `src/`.
const TOP_LEVEL: [&str; 6] = [
    "Cargo.toml",
    "README.md",
    ".cargo_vcs_info.json",
    ".cargo-ok",
    "PATCHED.md",
    "moonhaul.patch",
];

/// What a patched release is called in the messages.
const UPSTREAM: &str = "upstream + moonhaul.patch";

pub fn vendor_check() -> Result<(), String> {
    let root = workspace_root();
    let vendor = root.join("vendor");
    let mut dirs = Vec::new();
    for entry in
        fs::read_dir(&vendor).map_err(|e| format!("cannot read {}: {e}", vendor.display()))?
    {
        let entry = entry.map_err(|e| format!("cannot read {}: {e}", vendor.display()))?;
        if entry.path().is_dir() {
            dirs.push(entry.file_name().to_string_lossy().into_owned());
        }
    }
    dirs.sort();
    let mut failures = Vec::new();
    for dir in &dirs {
        match check_crate(&root, dir) {
            Ok(summary) => println!("vendor-check: {summary}"),
            Err(message) => failures.push(message),
        }
    }
    if failures.is_empty() {
        Ok(())
    } else {
        Err(format!("vendor-check failed\n{}", failures.join("\n")))
    }
}

/// Checks `vendor/<dir>`; the summary line on success, every difference on failure.
fn check_crate(root: &Path, dir: &str) -> Result<String, String> {
    let vendored = root.join("vendor").join(dir);
    let rel = format!("vendor/{dir}");
    let manifest_path = vendored.join("Cargo.toml");
    let manifest = fs::read_to_string(&manifest_path)
        .map_err(|e| format!("{rel}: cannot read {}: {e}", manifest_path.display()))?;
    let (name, version) = package_name_version(&manifest)
        .ok_or_else(|| format!("{rel}/Cargo.toml: no [package] name and version"))?;
    let checksum = CHECKSUMS
        .iter()
        .find(|(n, v, _)| *n == name && *v == version)
        .map(|(_, _, sum)| *sum)
        .ok_or_else(|| {
            format!(
                "{rel}: no pinned checksum for {name} {version}: add the `cksum` of version \
                 {version} from {} to CHECKSUMS in xtask/src/vendor_check.rs",
                index_url(&name)
            )
        })?;
    let crate_file = fetch_crate(&name, &version, checksum)?;

    let tmp = TempDir::new(&format!("{name}-{version}"))?;
    run(Command::new("tar")
        .arg("-xzf")
        .arg(&crate_file)
        .arg("-C")
        .arg(&tmp.0))
    .map_err(|e| format!("{rel}: cannot unpack {}: {e}", crate_file.display()))?;
    let upstream = tmp.0.join(format!("{name}-{version}"));
    // `git apply` inside another repository's work tree (a temp dir under a checkout) applies
    // paths relative to that tree's top: a repository of its own keeps them relative to here.
    run(Command::new("git")
        .current_dir(&upstream)
        .args(["init", "--quiet"]))
    .map_err(|e| format!("{rel}: {e}"))?;
    let patch = vendored.join("moonhaul.patch");
    let applied = Command::new("git")
        .current_dir(&upstream)
        .args(["apply", "--whitespace=nowarn"])
        .arg(&patch)
        .output()
        .map_err(|e| format!("{rel}: cannot start git: {e}"))?;
    if !applied.status.success() {
        return Err(format!(
            "{rel}/moonhaul.patch does not apply to {name} {version}: {}{}",
            String::from_utf8_lossy(&applied.stderr).trim(),
            regenerate_hint(dir, &name, &version, &crate_file)
        ));
    }

    let mut differences = Vec::new();
    let files = compare_trees(&upstream.join("src"), &vendored.join("src"), "src")?;
    differences.extend(files.differences);
    let upstream_manifest = fs::read_to_string(upstream.join("Cargo.toml"))
        .map_err(|e| format!("{rel}: cannot read the release's Cargo.toml: {e}"))?;
    if let Some(d) = compare_bytes(
        "Cargo.toml",
        strip_targets(&upstream_manifest).as_bytes(),
        manifest.as_bytes(),
    ) {
        differences.push(format!(
            "{d} (compared with the release's manifest less its [[test]]/[[example]]/[[bench]] \
             sections)"
        ));
    }
    for file in ["README.md", ".cargo_vcs_info.json"] {
        differences.extend(compare_file(
            &upstream.join(file),
            &vendored.join(file),
            file,
        )?);
    }
    for entry in fs::read_dir(&vendored).map_err(|e| format!("cannot read {rel}: {e}"))? {
        let entry = entry.map_err(|e| format!("cannot read {rel}: {e}"))?;
        let file = entry.file_name().to_string_lossy().into_owned();
        if file != "src" && !TOP_LEVEL.contains(&file.as_str()) {
            differences.push(format!(
                "{file}: only in {rel} (a vendored crate keeps src/, Cargo.toml, README.md and \
                 .cargo_vcs_info.json from the release, PATCHED.md and moonhaul.patch)"
            ));
        }
    }
    if differences.is_empty() {
        Ok(format!(
            "{name} {version} = {UPSTREAM} ({} files in src/; Cargo.toml less its test, example \
             and bench targets; README.md)",
            files.compared
        ))
    } else {
        Err(format!(
            "{rel} is not {name} {version} {}:\n  {}{}",
            UPSTREAM.trim_start_matches("upstream "),
            differences.join("\n  "),
            regenerate_hint(dir, &name, &version, &crate_file)
        ))
    }
}

/// How to make `moonhaul.patch` the whole change again, run from the workspace root.
fn regenerate_hint(dir: &str, name: &str, version: &str, crate_file: &Path) -> String {
    format!(
        "\n  If the vendored src/ is what is meant, regenerate the patch from the workspace root \
         with\n    t=$(mktemp -d) && mkdir \"$t/a\" \"$t/b\" && tar -xzf {} -C \"$t\" && mv \
         \"$t/{name}-{version}/src\" \"$t/a/\" && cp -r vendor/{dir}/src \"$t/b/\" && (cd \"$t\" \
         && diff -ruN a/src b/src) > vendor/{dir}/moonhaul.patch\n  otherwise restore the \
         differing files (`git checkout -- vendor/{dir}`); the manifest and README stay as \
         released.",
        crate_file.display()
    )
}

/// `name` and `version` from a manifest's `[package]` table (crates.io writes each as
/// `key = "value"` on its own line).
fn package_name_version(manifest: &str) -> Option<(String, String)> {
    let mut in_package = false;
    let (mut name, mut version) = (None, None);
    for line in manifest.lines().map(str::trim) {
        if line.starts_with('[') {
            in_package = line == "[package]";
            continue;
        }
        if !in_package {
            continue;
        }
        if let Some((key, value)) = line.split_once('=') {
            let value = value.trim().trim_matches('"').to_owned();
            match key.trim() {
                "name" => name = Some(value),
                "version" => version = Some(value),
                _ => {}
            }
        }
    }
    Some((name?, version?))
}

/// The manifest without its `[[test]]`, `[[example]]` and `[[bench]]` sections: each runs from
/// its header to the next table header (or the end), blank lines included.
fn strip_targets(manifest: &str) -> String {
    let mut kept = String::with_capacity(manifest.len());
    let mut skipping = false;
    for line in manifest.split_inclusive('\n') {
        let header = line.trim();
        if header.starts_with('[') {
            skipping = matches!(header, "[[test]]" | "[[example]]" | "[[bench]]");
        }
        if !skipping {
            kept.push_str(line);
        }
    }
    kept
}

/// The sparse-index URL holding a crate's published checksums.
fn index_url(name: &str) -> String {
    let prefix = match name.len() {
        1 => "1".to_owned(),
        2 => "2".to_owned(),
        3 => format!("3/{}", &name[..1]),
        _ => format!("{}/{}", &name[..2], &name[2..4]),
    };
    format!("https://index.crates.io/{prefix}/{name}")
}

fn cache_dir() -> Option<PathBuf> {
    let cargo_home = env::var_os("CARGO_HOME")
        .map(PathBuf::from)
        .or_else(|| env::var_os("HOME").map(|home| PathBuf::from(home).join(".cargo")))?;
    let dir = cargo_home
        .join("registry")
        .join("cache")
        .join("moonhaul-vendor-check");
    fs::create_dir_all(&dir).ok()?;
    Some(dir)
}

/// The release's `.crate`, from the cache or downloaded into it, its SHA-256 verified either way.
fn fetch_crate(name: &str, version: &str, checksum: &str) -> Result<PathBuf, String> {
    let file_name = format!("{name}-{version}.crate");
    let dir = cache_dir().unwrap_or_else(|| {
        let dir = env::temp_dir();
        eprintln!(
            "xtask: no writable cargo home for the download cache: {file_name} is kept in {} \
             instead",
            dir.display()
        );
        dir
    });
    let path = dir.join(&file_name);
    if let Ok(bytes) = fs::read(&path) {
        let sum = hex_sha256(&bytes);
        if sum == checksum {
            return Ok(path);
        }
        eprintln!(
            "xtask: cached {} has SHA-256 {sum}, not {checksum}: downloading it again",
            path.display()
        );
    }
    let url = format!("https://static.crates.io/crates/{name}/{file_name}");
    let partial = dir.join(format!("{file_name}.part"));
    stage(&format!("downloading {url} (once)"), || {
        download(&url, &partial)
    })?;
    let bytes =
        fs::read(&partial).map_err(|e| format!("cannot read {}: {e}", partial.display()))?;
    let sum = hex_sha256(&bytes);
    if sum != checksum {
        let _ = fs::remove_file(&partial);
        return Err(format!(
            "{url}: SHA-256 {sum}, but crates.io publishes {checksum} for {name} {version}"
        ));
    }
    fs::rename(&partial, &path).map_err(|e| {
        format!(
            "cannot move {} to {}: {e}",
            partial.display(),
            path.display()
        )
    })?;
    Ok(path)
}

/// Downloads `url` to `dest` with python3's urllib (see the module comment for why).
fn download(url: &str, dest: &Path) -> Result<(), String> {
    const SCRIPT: &str = "import shutil, sys, urllib.request
try:
    with urllib.request.urlopen(sys.argv[1], timeout=120) as r, open(sys.argv[2], 'wb') as f:
        shutil.copyfileobj(r, f)
except Exception as e:
    sys.exit(str(e))";
    let output = Command::new("python3")
        .args(["-c", SCRIPT, url])
        .arg(dest)
        .output()
        .map_err(|e| format!("cannot download {url}: cannot start python3: {e}"))?;
    if output.status.success() {
        Ok(())
    } else {
        let _ = fs::remove_file(dest);
        Err(format!(
            "cannot download {url}: {}",
            String::from_utf8_lossy(&output.stderr).trim()
        ))
    }
}

/// The outcome of comparing two trees.
#[derive(Debug)]
struct TreeComparison {
    /// Files present on both sides.
    compared: usize,
    /// One line per difference, naming the file by `label`/its relative path.
    differences: Vec<String>,
}

/// Compares every file under `expected` (the patched release) with `actual` (the vendored copy),
/// both ways, byte for byte. Paths in the messages start with `label`.
fn compare_trees(expected: &Path, actual: &Path, label: &str) -> Result<TreeComparison, String> {
    let want = list_files(expected)?;
    let have = list_files(actual)?;
    let mut result = TreeComparison {
        compared: 0,
        differences: Vec::new(),
    };
    for rel in want.union(&have) {
        let shown = format!("{label}/{rel}");
        match (want.contains(rel), have.contains(rel)) {
            (true, false) => result.differences.push(format!(
                "{shown}: missing from the vendored copy ({UPSTREAM} has it)"
            )),
            (false, true) => result.differences.push(format!(
                "{shown}: only in the vendored copy, not in {UPSTREAM}"
            )),
            _ => {
                result.compared += 1;
                result.differences.extend(compare_file(
                    &expected.join(rel),
                    &actual.join(rel),
                    &shown,
                )?);
            }
        }
    }
    Ok(result)
}

/// Every file under `dir`, as `/`-separated paths relative to it (sorted).
fn list_files(dir: &Path) -> Result<BTreeSet<String>, String> {
    fn walk(dir: &Path, prefix: &str, out: &mut BTreeSet<String>) -> Result<(), String> {
        let entries =
            fs::read_dir(dir).map_err(|e| format!("cannot read {}: {e}", dir.display()))?;
        for entry in entries {
            let entry = entry.map_err(|e| format!("cannot read {}: {e}", dir.display()))?;
            let name = entry.file_name().to_string_lossy().into_owned();
            let rel = if prefix.is_empty() {
                name
            } else {
                format!("{prefix}/{name}")
            };
            if entry.path().is_dir() {
                walk(&entry.path(), &rel, out)?;
            } else {
                out.insert(rel);
            }
        }
        Ok(())
    }
    let mut out = BTreeSet::new();
    walk(dir, "", &mut out)?;
    Ok(out)
}

/// Compares two files that should both exist (or both not), byte for byte.
fn compare_file(expected: &Path, actual: &Path, shown: &str) -> Result<Option<String>, String> {
    let read = |path: &Path| match fs::read(path) {
        Ok(bytes) => Ok(Some(bytes)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(format!("cannot read {}: {e}", path.display())),
    };
    Ok(match (read(expected)?, read(actual)?) {
        (None, None) => None,
        (Some(_), None) => Some(format!(
            "{shown}: missing from the vendored copy ({UPSTREAM} has it)"
        )),
        (None, Some(_)) => Some(format!(
            "{shown}: only in the vendored copy, not in {UPSTREAM}"
        )),
        (Some(want), Some(have)) => compare_bytes(shown, &want, &have),
    })
}

/// `None` when equal, else the file and its first differing line.
fn compare_bytes(shown: &str, want: &[u8], have: &[u8]) -> Option<String> {
    if want == have {
        return None;
    }
    let excerpt = |line: Option<&[u8]>| match line {
        None => "(end of file)".to_owned(),
        Some(line) => {
            let text = String::from_utf8_lossy(line);
            let text = text.trim_end();
            let cut: String = text.chars().take(100).collect();
            if cut.len() < text.len() {
                format!("`{cut}…`")
            } else {
                format!("`{cut}`")
            }
        }
    };
    let mut want_lines = want.split_inclusive(|&b| b == b'\n');
    let mut have_lines = have.split_inclusive(|&b| b == b'\n');
    let mut number = 1;
    loop {
        let (w, h) = (want_lines.next(), have_lines.next());
        if w != h {
            let (w, h) = (excerpt(w), excerpt(h));
            let note = if w == h {
                " (they differ in trailing whitespace or the line ending)"
            } else {
                ""
            };
            return Some(format!(
                "{shown} differs from line {number}: {UPSTREAM} has {w}, the vendored copy {h}{note}"
            ));
        }
        number += 1;
    }
}

/// A directory under the system temp dir, removed when dropped.
struct TempDir(PathBuf);

impl TempDir {
    fn new(tag: &str) -> Result<Self, String> {
        let path = env::temp_dir().join(format!(
            "moonhaul-vendor-check-{}-{tag}",
            std::process::id()
        ));
        let _ = fs::remove_dir_all(&path);
        fs::create_dir_all(&path).map_err(|e| format!("cannot create {}: {e}", path.display()))?;
        Ok(Self(path))
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = fs::remove_dir_all(&self.0);
    }
}

/// The lower-case hex SHA-256 of `bytes`, as crates.io writes its checksums.
fn hex_sha256(bytes: &[u8]) -> String {
    Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two identical trees with a nested directory, in a fresh temp dir.
    fn trees(tag: &str) -> TempDir {
        let tmp = TempDir::new(&format!("test-{tag}")).unwrap();
        for side in ["want", "have"] {
            let dir = tmp.0.join(side).join("nested");
            fs::create_dir_all(&dir).unwrap();
            fs::write(tmp.0.join(side).join("lib.rs"), "pub mod nested;\n").unwrap();
            fs::write(dir.join("mod.rs"), "fn a() {}\nfn b() {}\nfn c() {}\n").unwrap();
        }
        tmp
    }

    fn compare(tmp: &TempDir) -> TreeComparison {
        compare_trees(&tmp.0.join("want"), &tmp.0.join("have"), "src").unwrap()
    }

    #[test]
    fn checksums_are_hex_sha256() {
        // FIPS 180-2, appendix B.1.
        assert_eq!(
            hex_sha256(b"abc"),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
    }

    #[test]
    fn identical_trees_pass() {
        let tmp = trees("same");
        let result = compare(&tmp);
        assert_eq!(result.compared, 2);
        assert!(result.differences.is_empty(), "{:?}", result.differences);
    }

    #[test]
    fn a_changed_byte_names_the_file_and_line() {
        let tmp = trees("byte");
        fs::write(
            tmp.0.join("have/nested/mod.rs"),
            "fn a() {}\nfn B() {}\nfn c() {}\n",
        )
        .unwrap();
        let result = compare(&tmp);
        assert_eq!(result.differences.len(), 1, "{:?}", result.differences);
        let message = &result.differences[0];
        assert!(
            message.starts_with("src/nested/mod.rs differs from line 2:"),
            "{message}"
        );
        assert!(message.contains("`fn b() {}`") && message.contains("`fn B() {}`"));
    }

    #[test]
    fn a_missing_and_an_extra_file_are_differences() {
        let tmp = trees("missing-extra");
        fs::remove_file(tmp.0.join("have/lib.rs")).unwrap();
        fs::write(tmp.0.join("have/nested/extra.rs"), "").unwrap();
        let result = compare(&tmp);
        assert_eq!(result.compared, 1);
        assert_eq!(result.differences.len(), 2, "{:?}", result.differences);
        assert!(result.differences[0].starts_with("src/lib.rs: missing from the vendored copy"));
        assert!(result.differences[1].starts_with("src/nested/extra.rs: only in the vendored copy"));
    }

    #[test]
    fn a_truncated_file_is_a_difference() {
        let diff = compare_bytes("f", b"a\nb\n", b"a\n").unwrap();
        assert!(diff.starts_with("f differs from line 2:"), "{diff}");
        assert!(diff.contains("(end of file)"), "{diff}");
        assert_eq!(compare_bytes("f", b"a\n", b"a\n"), None);
        let diff = compare_bytes("f", b"a\nb\n", b"a\nb").unwrap();
        assert!(
            diff.contains("line 2") && diff.contains("line ending"),
            "{diff}"
        );
    }

    #[test]
    fn strip_targets_removes_only_target_sections() {
        let released = "[package]\nname = \"x\"\nversion = \"1.0.0\"\n\n[lib]\npath = \"src/lib.rs\"\n\n\
                        [[example]]\nname = \"e\"\npath = \"examples/e.rs\"\n\n[[test]]\nname = \"t\"\n\n\
                        [[bench]]\nname = \"b\"\n\n[dependencies.y]\nversion = \"2\"\n";
        let vendored =
            "[package]\nname = \"x\"\nversion = \"1.0.0\"\n\n[lib]\npath = \"src/lib.rs\"\n\n\
                        [dependencies.y]\nversion = \"2\"\n";
        assert_eq!(strip_targets(released), vendored);
        assert_eq!(
            package_name_version(released),
            Some(("x".to_owned(), "1.0.0".to_owned()))
        );
    }

    #[test]
    fn index_urls_follow_the_sparse_layout() {
        assert_eq!(
            index_url("rapier3d"),
            "https://index.crates.io/ra/pi/rapier3d"
        );
        assert_eq!(index_url("syn"), "https://index.crates.io/3/s/syn");
        assert_eq!(index_url("cc"), "https://index.crates.io/2/cc");
    }
}
