//! `moonhaul keys`: the team key files that authenticate peer and operator messages (frame
//! format, key-file layout and threat model in `moonhaul_coord::auth`).
//!
//! Key files are secrets and live **outside the repository and its `configs/`**; the
//! recommended place is `~/.config/moonhaul/<team>.keys.toml` on every unit and on the
//! operator console (each gets a copy of the same file, over a channel you trust). The unit
//! daemon reads it with `--keys FILE`. Rotating keys: generate a new file with a higher
//! `--epoch` and give it to every member; frames under the old epoch are rejected from then on.
//!
//! The same file provisions the network: every zenoh session (unit, simulated world, operator
//! console) authenticates with a user/password derived from it (`unit-<i>@<team>`,
//! `operator@<team>`, `world@<team>`; the password an HMAC of the role's key), and zenoh's
//! access control lets each role publish only its own keys. Nothing else is generated or copied;
//! rotating the file rotates them (`moonhaul_deploy::network` documents the scheme).

use std::path::{Path, PathBuf};

use anyhow::Context;
use moonhaul_coord::auth::{KeyFileError, MAX_KEY_FILE_UNITS};
use moonhaul_coord::KeyFile;

#[derive(clap::Subcommand)]
pub enum KeysCommand {
    /// Generate a new team key file: one random 32-byte secret per unit and one for the
    /// operator, from the operating system's random source. Written with mode 0600; the
    /// secrets are never printed. Keep key files outside the repository, e.g.
    /// `~/.config/moonhaul/<team>.keys.toml`, and start each unit daemon with `--keys FILE`.
    Generate(GenerateArgs),
}

#[derive(clap::Args)]
pub struct GenerateArgs {
    /// Team name; must equal `team` in every unit's `configs/unit.toml`.
    #[arg(long, value_name = "NAME")]
    team: String,
    /// Number of units in the team (keys for units 0..N-1, plus the operator).
    #[arg(long, value_name = "N", value_parser = parse_units)]
    units: usize,
    /// Key epoch; bump it whenever keys are rotated (frames under another epoch are refused).
    #[arg(long, value_name = "E", default_value_t = 1)]
    epoch: u32,
    /// Where to write the key file, e.g. `~/.config/moonhaul/<team>.keys.toml` (outside the
    /// repository). A missing folder is created, private (0700).
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
    /// Replace an existing key file (rotation); without it an existing file is never touched.
    #[arg(long)]
    force: bool,
}

fn parse_units(text: &str) -> Result<usize, String> {
    let units: usize = text
        .parse()
        .map_err(|_| format!("{text:?} is not a whole number of units"))?;
    if !(1..=MAX_KEY_FILE_UNITS).contains(&units) {
        return Err(format!(
            "a team has 1 to {MAX_KEY_FILE_UNITS} units, not {units}"
        ));
    }
    Ok(units)
}

pub fn run(cmd: KeysCommand) -> anyhow::Result<()> {
    match cmd {
        KeysCommand::Generate(args) => generate(&args),
    }
}

fn generate(args: &GenerateArgs) -> anyhow::Result<()> {
    let out = &args.out;
    let keys = KeyFile::generate(&args.team, args.units, args.epoch)
        .context("cannot generate team keys")?;
    create_private_parent(out)?;
    let replaced = args.force && out.exists();
    match keys.write_new(out, args.force) {
        Ok(()) => {}
        Err(e @ KeyFileError::Exists { .. }) => {
            return Err(anyhow::Error::new(e).context(
                "not replacing the team's keys; pass --force to rotate them (every unit and \
                 the operator then needs the new file)",
            ))
        }
        Err(e) => {
            return Err(e).with_context(|| format!("cannot write the key file {}", out.display()))
        }
    }
    outln!(
        "{} team key file {} (mode 0600)",
        if replaced { "replaced" } else { "wrote" },
        out.display()
    )?;
    outln!(
        "  team {:?}, key epoch {}, keys for {} units and the operator",
        keys.team(),
        keys.epoch(),
        keys.team_size()
    )?;
    outln!(
        "  copy it to every unit and the operator console over a trusted channel, keep it \
         mode 0600 outside the repository, and start each daemon with --keys FILE"
    )
}

/// Creates the key file's folder if it is missing, readable by its owner only.
fn create_private_parent(out: &Path) -> anyhow::Result<()> {
    let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) else {
        return Ok(());
    };
    if dir.exists() {
        return Ok(());
    }
    let mut builder = std::fs::DirBuilder::new();
    builder.recursive(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::DirBuilderExt as _;
        builder.mode(0o700);
    }
    builder
        .create(dir)
        .with_context(|| format!("cannot create the folder {}", dir.display()))
}
