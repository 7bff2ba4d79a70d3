//! The `pipeline` command-line tool: builds the stage registry from every stage crate and
//! hands the command to the engine.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use seqavatar_compute::backend::{Backend, DeviceChoice};
use seqavatar_engine::RunOptions;
use seqavatar_engine::commands::{self, InspectOptions};

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
        /// Re-check every cached entry against its manifest digests (reads every file).
        #[arg(long)]
        verify: bool,
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
    /// Render a trained avatar driven by the poses of another sequence or a pose file (PNG
    /// frames, and an MP4 when ffmpeg is on PATH).
    Render {
        /// The train entry: its cache folder, its key or a unique key prefix.
        #[arg(long, value_parser = entry_spec)]
        avatar: String,
        /// An ingest entry (folder, key or key prefix) or a pose file (.npz with body_pose,
        /// global_orient, transl and optionally betas).
        #[arg(long, value_parser = entry_spec)]
        poses: String,
        /// View index of the avatar's training cameras.
        #[arg(long, default_value_t = 0)]
        camera: usize,
        /// Image size factor applied to that camera.
        #[arg(long, default_value_t = 1.0)]
        resolution_scale: f64,
        /// Output folder for frame_NNNNN.png and render.mp4.
        #[arg(long)]
        out: PathBuf,
        /// Backend: auto, cpu or gpu.
        #[arg(long, default_value_t = DeviceChoice::Auto)]
        device: DeviceChoice,
        /// Frames per second of the MP4.
        #[arg(long, default_value_t = 25)]
        fps: u32,
        /// Render at most this many frames (0 = all).
        #[arg(long, default_value_t = 0)]
        max_frames: usize,
    },
    /// Export a trained avatar's Gaussians as standard 3D Gaussian Splatting PLY files:
    /// canonical.ply, and with --poses one frame_NNNNN.ply per frame, posed as `render` poses
    /// them (they open in the common splat viewers and editors).
    Export {
        /// The train entry: its cache folder, its key or a unique key prefix.
        #[arg(long, value_parser = entry_spec)]
        avatar: String,
        /// An ingest entry (folder, key or key prefix) or a pose file (.npz with body_pose,
        /// global_orient, transl and optionally betas); without it, canonical.ply only.
        #[arg(long, value_parser = entry_spec)]
        poses: Option<String>,
        /// Output folder for canonical.ply and frame_NNNNN.ply.
        #[arg(long)]
        out: PathBuf,
        /// Backend of the networks: auto, cpu or gpu.
        #[arg(long, default_value_t = DeviceChoice::Auto)]
        device: DeviceChoice,
        /// Export at most this many frames (0 = all).
        #[arg(long, default_value_t = 0)]
        max_frames: usize,
    },
    /// Serve a web page that shows a trained avatar rendered live: orbit, pan and zoom,
    /// the dataset cameras, a timeline with play, ground truth and error map, the motion
    /// context on, zeroed or from another frame.
    View {
        /// FILE.yaml:TRAIN_STAGE (its cached entry), unless --avatar names the entry.
        target: Option<String>,
        /// The train entry: its cache folder, its key or a unique key prefix.
        #[arg(long, conflicts_with = "target", value_parser = entry_spec)]
        avatar: Option<String>,
        /// Drive the avatar with these poses: an ingest entry (folder, key or key prefix) or
        /// a pose file (.npz); default: its trained sequence, with its ground-truth images.
        #[arg(long, value_parser = entry_spec)]
        poses: Option<String>,
        /// Address to listen on; anything but a loopback address exposes the viewer to the
        /// network, needs --allow-remote and makes the viewer ask for an access token.
        #[arg(long, default_value = "127.0.0.1")]
        host: String,
        /// Allow a --host that is not a loopback address: the viewer then answers only
        /// requests carrying the random access token of its printed URL (over plain HTTP,
        /// unencrypted: anyone who sees the URL or the traffic can use it).
        #[arg(long)]
        allow_remote: bool,
        /// Port to listen on (0: a free port; the URL is printed).
        #[arg(long, default_value_t = 8080)]
        port: u16,
        /// Backend: auto, cpu or gpu.
        #[arg(long, default_value_t = DeviceChoice::Auto)]
        device: DeviceChoice,
        /// The largest image side the page may ask for.
        #[arg(long, default_value_t = seqavatar_viewer::DEFAULT_MAX_SIZE)]
        max_size: u32,
        /// Override a config value when TARGET is FILE.yaml:STAGE.
        #[arg(long = "set", value_name = "STAGE.KEY=VALUE")]
        sets: Vec<String>,
    },
    /// Write a Markdown report with PNG plots (metrics, loss curves, stage timing, cache
    /// reuse, trade-off and Pareto plots for sweeps) from a pipeline's cached entries.
    Report {
        /// Pipeline YAML file.
        file: PathBuf,
        /// Output folder [default: reports/<pipeline file stem>].
        #[arg(long)]
        out: Option<PathBuf>,
        /// Override a config value: stage.key=value.
        #[arg(long = "set", value_name = "STAGE.KEY=VALUE")]
        sets: Vec<String>,
    },
    /// Remove cache entries that none of the listed pipelines references.
    Gc {
        /// Pipelines whose entries are kept (repeatable).
        #[arg(long)]
        keep: Vec<PathBuf>,
        /// Overrides `stage.key=value` applied to every `--keep` pipeline, as given to `run`
        /// (repeatable), so the entries of `run FILE --set ...` are kept.
        #[arg(long = "set", value_name = "STAGE.KEY=VALUE")]
        sets: Vec<String>,
        /// Only print what would be removed.
        #[arg(long)]
        dry_run: bool,
    },
}

fn execute(cli: Cli) -> anyhow::Result<()> {
    let registry = seqavatar_registry::registry();
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
        Command::Status { file, verify, sets } => {
            commands::status(&registry, &file, &sets, verify, &cache)?
        }
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
        Command::Gc {
            keep,
            sets,
            dry_run,
        } => {
            commands::gc(&registry, &keep, &sets, dry_run, &cache)?;
        }
        Command::Render {
            avatar,
            poses,
            camera,
            resolution_scale,
            out,
            device,
            fps,
            max_frames,
        } => {
            let backend = Backend::select(device)?;
            let options = seqavatar_evaluation::animate::RenderOptions {
                avatar,
                poses: seqavatar_evaluation::animate::PoseSource::parse(&poses),
                camera,
                resolution_scale,
                out,
                backend,
                fps,
                max_frames,
            };
            let summary = seqavatar_evaluation::animate::render_poses(&cache, &options)?;
            println!(
                "rendered {} frames into {} in {:.2} s",
                summary.frames.len(),
                options.out.display(),
                summary.seconds
            );
            print_skipped(summary.skipped);
            match (&summary.video, &summary.video_note) {
                (Some(video), _) => println!("video: {}", video.display()),
                (None, Some(note)) => println!("{note}"),
                (None, None) => {}
            }
        }
        Command::Export {
            avatar,
            poses,
            out,
            device,
            max_frames,
        } => {
            let backend = Backend::select(device)?;
            let options = seqavatar_evaluation::export::ExportOptions {
                avatar,
                poses: poses
                    .as_deref()
                    .map(seqavatar_evaluation::animate::PoseSource::parse),
                out,
                backend,
                max_frames,
                progress: std::io::IsTerminal::is_terminal(&std::io::stderr()),
            };
            let summary = seqavatar_evaluation::export::export_avatar(&cache, &options)?;
            println!(
                "wrote {} ({} Gaussians) and {} posed frames into {} in {:.2} s",
                summary.canonical.display(),
                summary.gaussians,
                summary.frames.len(),
                options.out.display(),
                summary.seconds
            );
            print_skipped(summary.skipped);
        }
        Command::View {
            target,
            avatar,
            poses,
            host,
            allow_remote,
            port,
            device,
            max_size,
            sets,
        } => {
            check_view_host(&host, allow_remote)?;
            let avatar = match (target, avatar) {
                (_, Some(avatar)) => avatar,
                (Some(target), None) => {
                    let (file, stage) = seqavatar_viewer::split_pipeline_target(&target)
                        .ok_or_else(|| {
                            anyhow::anyhow!(
                                "{target}: expected FILE.yaml:TRAIN_STAGE (or give --avatar)"
                            )
                        })?;
                    seqavatar_viewer::train_key_of_stage(&registry, file, stage, &sets, &cache)?
                }
                (None, None) => {
                    anyhow::bail!("give FILE.yaml:TRAIN_STAGE or --avatar <train entry>")
                }
            };
            let options = seqavatar_viewer::ViewerOptions {
                cache,
                avatar,
                poses: poses
                    .as_deref()
                    .map(seqavatar_evaluation::animate::PoseSource::parse),
                backend: Backend::select(device)?,
                host,
                port,
                max_size,
            };
            let viewer = seqavatar_viewer::Viewer::start(options)?;
            let address = viewer.address();
            if !address.ip().is_loopback() {
                eprintln!(
                    "warning: listening on {address}{}: anyone with the URL, token included, \
                     can use the viewer; HTTP is not encrypted, so share it only on a network \
                     you trust",
                    if address.ip().is_unspecified() {
                        " (every network interface)"
                    } else {
                        ""
                    }
                );
            }
            println!(
                "viewer: {} (listening on {address}; Ctrl-C to stop)",
                viewer.url()
            );
            viewer.wait()?;
        }
        Command::Report { file, out, sets } => {
            let out = out.unwrap_or_else(|| {
                let stem = file
                    .file_stem()
                    .map(|stem| stem.to_string_lossy().into_owned())
                    .unwrap_or_else(|| "pipeline".to_owned());
                PathBuf::from("reports").join(stem)
            });
            let path = seqavatar_evaluation::pipeline_report::write_report(
                &registry, &file, &sets, &cache, &out,
            )?;
            println!("report: {}", path.display());
        }
    }
    Ok(())
}

/// Says which leading frames `render` or `export` skipped (`skipped` of them), if any.
fn print_skipped(skipped: usize) {
    if skipped > 0 {
        println!(
            "skipped frames 0..{skipped}: their motion windows reach before the first frame of the pose entry"
        );
    }
}

/// An entry named on the command line (a cache entry folder, a key or a key prefix, or a
/// pose file): an empty name is the prefix of every key, so it is refused.
fn entry_spec(text: &str) -> Result<String, String> {
    if text.trim().is_empty() {
        return Err(
            "an empty name would match every entry; give a cache entry folder, a key or a \
             unique key prefix"
                .to_owned(),
        );
    }
    Ok(text.to_owned())
}

/// Whether `host` (a name or an address, IPv6 in brackets or not) is a loopback address.
fn is_loopback_host(host: &str) -> bool {
    host.eq_ignore_ascii_case("localhost")
        || host
            .trim_start_matches('[')
            .trim_end_matches(']')
            .parse::<std::net::IpAddr>()
            .is_ok_and(|ip| ip.is_loopback())
}

/// `pipeline view` listens beyond loopback only when asked to with `--allow-remote`.
fn check_view_host(host: &str, allow_remote: bool) -> anyhow::Result<()> {
    if !allow_remote && !is_loopback_host(host) {
        anyhow::bail!(
            "--host {host} is not a loopback address: the viewer would be reachable from the \
             network (guarded by an access token in its URL); add --allow-remote to mean that"
        );
    }
    Ok(())
}

fn main() -> ExitCode {
    // Before any thread allocates: training frees and re-allocates the same large buffers
    // every iteration, and returning them to the kernel cost 15-20% of its time.
    seqavatar_compute::memory::retain_freed_memory();
    match execute(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("error: {error:#}");
            ExitCode::FAILURE
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(arguments: &[&str]) -> Result<Cli, String> {
        Cli::try_parse_from(std::iter::once("pipeline").chain(arguments.iter().copied()))
            .map_err(|error| error.to_string())
    }

    /// `render --avatar ''` once picked an entry (every key starts with ""): refused.
    #[test]
    fn an_empty_entry_name_is_refused() {
        for arguments in [
            &["render", "--avatar", "", "--poses", "abc", "--out", "o"][..],
            &["render", "--avatar", "abc", "--poses", " ", "--out", "o"],
            &["export", "--avatar", "", "--out", "o"],
            &["view", "--avatar", ""],
        ] {
            let error = parse(arguments).unwrap_err();
            assert!(
                error.contains("an empty name would match every entry"),
                "{error}"
            );
        }
        parse(&["render", "--avatar", "ab", "--poses", "cd", "--out", "o"]).unwrap();
    }

    #[test]
    fn viewing_beyond_loopback_needs_allow_remote() {
        for host in ["127.0.0.1", "localhost", "::1", "[::1]", "127.0.0.2"] {
            check_view_host(host, false).unwrap();
        }
        for host in ["0.0.0.0", "192.168.1.5", "::", "example.org"] {
            let error = check_view_host(host, false).unwrap_err().to_string();
            assert!(error.contains("--allow-remote"), "{error}");
            check_view_host(host, true).unwrap();
        }
        let Cli {
            command: Command::View { allow_remote, .. },
            ..
        } = parse(&[
            "view",
            "--avatar",
            "k",
            "--host",
            "0.0.0.0",
            "--allow-remote",
        ])
        .unwrap()
        else {
            panic!("not the view command");
        };
        assert!(allow_remote);
    }
}
