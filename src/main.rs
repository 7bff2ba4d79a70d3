//! The `pipeline` command-line tool: builds the stage registry from every stage crate and
//! hands the command to the engine.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use seqavatar_engine::commands::{self, InspectOptions};
use seqavatar_engine::{Registry, RunOptions};

/// SeqAvatar: multi-view videos of a moving person to an animatable 3D Gaussian avatar.
#[derive(Debug, Parser)]
#[command(name = "pipeline", version, about)]
struct Cli {
    /// Cache folder, or s3://bucket/prefix for a shared remote cache fronted by the folder
    /// $SEQAVATAR_LOCAL_CACHE (else ./cache) [default: $SEQAVATAR_CACHE, else ./cache].
    #[arg(long, global = true)]
    cache: Option<PathBuf>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Run what is missing from the cache.
    Run {
        /// Pipeline YAML file.
        file: PathBuf,
        /// Run only this stage and the stages it depends on.
        #[arg(long)]
        until: Option<String>,
        /// Recompute this stage even when cached (repeatable).
        #[arg(long)]
        force: Vec<String>,
        /// Override a config value: stage.key=value (value parsed as YAML; repeatable).
        #[arg(long = "set", value_name = "STAGE.KEY=VALUE")]
        sets: Vec<String>,
    },
    /// Show for each stage whether it is cached, partial (resumable) or missing.
    Status {
        /// Pipeline YAML file.
        file: PathBuf,
        /// Override a config value: stage.key=value.
        #[arg(long = "set", value_name = "STAGE.KEY=VALUE")]
        sets: Vec<String>,
    },
    /// Print the arrays, statistics and provenance of an entry; export pictures.
    Inspect {
        /// FILE.yaml:STAGE[:ARRAY] or the folder of a cache entry (optionally /ARRAY).
        target: String,
        /// The array to show or export.
        #[arg(long)]
        array: Option<String>,
        /// Write a PNG of an image-like array (or of --picture).
        #[arg(long)]
        png: Option<PathBuf>,
        /// Write the raw floats of an image-like array as OpenEXR.
        #[arg(long)]
        exr: Option<PathBuf>,
        /// A picture the stage kind draws (see the `picture` lines of the output).
        #[arg(long)]
        picture: Option<String>,
        /// Picture option key=value (index, min, max, or stage-specific; repeatable).
        #[arg(long = "opt", value_name = "KEY=VALUE")]
        opts: Vec<String>,
        /// Override a config value when TARGET is FILE:STAGE.
        #[arg(long = "set", value_name = "STAGE.KEY=VALUE")]
        sets: Vec<String>,
    },
    /// Remove cache entries that none of the listed pipelines references.
    Gc {
        /// Pipelines whose entries are kept (repeatable).
        #[arg(long)]
        keep: Vec<PathBuf>,
        /// Only print what would be removed.
        #[arg(long)]
        dry_run: bool,
    },
}

fn registry() -> Registry {
    let mut registry = Registry::new();
    seqavatar_ingest::register(&mut registry);
    seqavatar_fit::register(&mut registry);
    seqavatar_motion::register(&mut registry);
    seqavatar_train::register(&mut registry);
    seqavatar_eval::register(&mut registry);
    registry
}

fn execute(cli: Cli) -> anyhow::Result<()> {
    let registry = registry();
    let cache = cli
        .cache
        .or_else(|| std::env::var_os("SEQAVATAR_CACHE").map(PathBuf::from))
        .unwrap_or_else(|| PathBuf::from("cache"));
    match cli.command {
        Command::Run {
            file,
            until,
            force,
            sets,
        } => {
            let options = RunOptions { until, force };
            commands::run(&registry, &file, &sets, &options, &cache)?;
        }
        Command::Status { file, sets } => commands::status(&registry, &file, &sets, &cache)?,
        Command::Inspect {
            target,
            array,
            png,
            exr,
            picture,
            opts,
            sets,
        } => {
            let options = InspectOptions {
                array,
                png,
                exr,
                picture,
                picture_options: opts,
                sets,
            };
            commands::inspect(&registry, &target, &options, &cache)?;
        }
        Command::Gc { keep, dry_run } => commands::gc(&registry, &keep, dry_run, &cache)?,
    }
    Ok(())
}

fn main() -> ExitCode {
    match execute(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("error: {error:#}");
            ExitCode::FAILURE
        }
    }
}
