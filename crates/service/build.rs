//! The store's migrations are embedded in the service: this writes the list of every
//! `migrations/<engine>/<version>_<description>.sql` file, with its text included, and
//! `store/backend.rs` hands it to sqlx's migrator. A new or changed file rebuilds the crate.
//! (sqlx's `migrate!` macro would do the same, at the cost of building both database drivers
//! a second time for the compiler.)

use std::error::Error;
use std::fmt::Write as _;
use std::path::PathBuf;

fn main() -> Result<(), Box<dyn Error>> {
    let root = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR")?).join("../../migrations");
    println!("cargo:rerun-if-changed=../../migrations");
    let mut out = String::new();
    for engine in ["sqlite", "postgres"] {
        let dir = root.join(engine).canonicalize()?;
        let mut names: Vec<String> = std::fs::read_dir(&dir)?
            .map(|e| e.map(|e| e.file_name().to_string_lossy().into_owned()))
            .collect::<Result<_, _>>()?;
        names.retain(|n| n.ends_with(".sql"));
        names.sort();
        writeln!(
            out,
            "pub const {}: &[(i64, &str, &str)] = &[",
            engine.to_uppercase()
        )?;
        for name in names {
            // As sqlx reads a directory: `<version>_<description>.sql`, underscores in the
            // description read as spaces. Only simple (not reversible) migrations are used.
            let (version, rest) = name
                .split_once('_')
                .ok_or_else(|| format!("migration {name}: expected <version>_<description>.sql"))?;
            let version: i64 = version
                .parse()
                .map_err(|_| format!("migration {name}: the version is not an integer"))?;
            if rest.ends_with(".up.sql") || rest.ends_with(".down.sql") {
                return Err(format!("migration {name}: reversible migrations are not used").into());
            }
            let description = rest.trim_end_matches(".sql").replace('_', " ");
            let path = dir.join(&name);
            writeln!(
                out,
                "    ({version}, {description:?}, include_str!({:?})),",
                path.display().to_string()
            )?;
        }
        writeln!(out, "];")?;
    }
    let dest = PathBuf::from(std::env::var("OUT_DIR")?).join("migrations.rs");
    std::fs::write(dest, out)?;
    Ok(())
}
