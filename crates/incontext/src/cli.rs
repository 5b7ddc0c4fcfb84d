//! The command line: flags, dispatch, output.

use clap::{Parser, Subcommand};
use serde_json::Value;

use crate::error::Result;

const AFTER_HELP: &str = "\
Examples:
  incontext demo --seed 3 --out demo-out
  incontext register --model obj_000001.ply --depth 000000.png --camera camera.json --out pose.json --overlay overlay.png
  incontext eval --dataset target/data --out eval-out
  incontext eval --cases cases --method ours-softmax,ours-softmax-icp --out results.jsonl
  incontext render --model obj_000001.ply --camera camera.json --pose pose.json --out rendered
  incontext train pose --objects my-meshes --out my-pose --minutes 30

Units: meshes are in the depth map's units after the camera's depth_scale, i.e. mm for BOP
(--model-unit-mm for other units). Poses map model to camera coordinates, x_cam = R·x + t,
R row-major in files.

Exit codes: 0 ok, 2 bad input (flags, files: the message names the file), 3 object not found
(including a best pose whose confidence is below the not_found threshold), 4 register's pose
is uncertain (written with \"verdict\": \"uncertain\"), 130 interrupted (no partial file
left), 1 internal error. With --json, stdout holds one JSON object: the result, or
{\"error\": …, \"kind\": …, \"exit_code\": …}.";

/// 6D pose of a known object in one depth map (Dang, Wang, Salzmann, CVPR 2021).
#[derive(Parser, Debug)]
#[command(name = "incontext", version, after_help = AFTER_HELP)]
pub struct Cli {
    /// Compute threads (default: all logical CPUs; more than that is capped to it).
    #[arg(long, global = true, help_heading = "Global options", value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..))]
    pub threads: Option<usize>,
    /// Seed of every random choice (point sampling; the demo's object and view).
    #[arg(
        long,
        global = true,
        help_heading = "Global options",
        default_value_t = 0
    )]
    pub seed: u64,
    /// More log output on stderr (-v debug, -vv trace).
    #[arg(short, long, global = true, help_heading = "Global options", action = clap::ArgAction::Count)]
    pub verbose: u8,
    /// Only errors on stderr.
    #[arg(short, long, global = true, help_heading = "Global options")]
    pub quiet: bool,
    /// Print one JSON object on stdout (the result or the error) instead of text.
    #[arg(long, global = true, help_heading = "Global options")]
    pub json: bool,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// The pose of a mesh in a depth map: segmentation, pose network on 24 rotated copies, ICP,
    /// render-and-compare verification.
    #[command(after_help = "\
Example:
  incontext register --model obj_000001.ply --depth scene/depth/000003.png --camera camera.json \\
      --out pose.json --overlay overlay.png --ply aligned.ply
  (an entry of a BOP scene_camera.json works as camera.json: cam_K, depth_scale; without
  width and height the depth map's size is used)

Output: the pose in the camera frame in the mesh's units (R row-major, t), the same as BOP's
cam_R_m2c / cam_t_m2c in mm, the confidence (fraction of the object's points the aligned model
explains) and the time of each stage.")]
    Register(crate::register::RegisterArgs),
    /// A self-contained demo: builds a scene, runs the pipeline, prints errors and timings.
    #[command(after_help = "\
Example:
  incontext demo --seed 3 --out demo-out
  incontext register --model demo-out/model.ply --depth demo-out/depth.png \\
      --camera demo-out/camera.json --seed 3      # the same pose, from the files")]
    Demo(crate::demo::DemoArgs),
    /// Our methods on a BOP dataset (tables, plots, BOP CSV) or on exported registration cases
    /// (one JSON line per case and method).
    #[command(after_help = "\
Examples:
  incontext eval --dataset target/data --out eval-out            # gen-data folder or BOP dataset
  incontext eval --cases target/cases --method ours-softmax-icp,ours-ot-icp --out results.jsonl")]
    Eval(crate::eval::EvalArgs),
    /// Render the depth map and mask of a mesh at a pose (to check a pose or make test data).
    #[command(after_help = "\
Example:
  incontext render --model obj_000001.ply --camera camera.json --pose pose.json --out rendered")]
    Render(crate::render::RenderArgs),
    /// Fine-tune the pose or segmentation network on your own meshes (views rendered on the
    /// fly); writes a checkpoint that register's --pose-model / --seg-model loads.
    #[command(after_help = "\
Examples:
  incontext train pose --objects my-meshes --out my-pose --minutes 30
  incontext register --pose-model my-pose/final.safetensors --model my-meshes/part.ply \\
      --depth depth.png --camera camera.json
  incontext train seg --objects my-meshes --out my-seg --iterations 500 --threads 4

Ctrl-C (or SIGTERM) saves a checkpoint and exits with code 130: continue with --resume.")]
    Train(crate::train::TrainArgs),
}

/// Runs a parsed command; returns its JSON report and the text for people.
pub fn run(cli: &Cli) -> Result<(Value, String)> {
    match &cli.command {
        Command::Register(a) => {
            let outcome = crate::register::register_files(a, cli.seed)?;
            let text = crate::register::summary_text(&outcome.report);
            Ok((outcome.report, text))
        }
        Command::Demo(a) => {
            let report = crate::demo::run(a, cli.seed)?;
            let text = crate::demo::summary_text(&report);
            Ok((report, text))
        }
        Command::Eval(a) => {
            let report = crate::eval::run(a, cli.seed)?;
            let text = match report["mode"].as_str() {
                Some("dataset") => format!(
                    "{}wrote {}\n",
                    report["tables"].as_str().unwrap_or(""),
                    report["config"]["out"].as_str().unwrap_or("?")
                ),
                _ => format!(
                    "{} results ({} failed), median seconds {}, wrote {}\n",
                    report["results"],
                    report["failed"],
                    report["median_seconds"],
                    report["out"].as_str().unwrap_or("?")
                ),
            };
            Ok((report, text))
        }
        Command::Train(a) => {
            let report = crate::train::run(a, cli.seed)?;
            let text = crate::train::summary_text(&report);
            Ok((report, text))
        }
        Command::Render(a) => {
            let report = crate::render::run(a)?;
            let text = format!(
                "{} object pixels; wrote {}, {}, {}\n",
                report["object_pixels"],
                report["outputs"]["depth_png"].as_str().unwrap_or("?"),
                report["outputs"]["depth_exr"].as_str().unwrap_or("?"),
                report["outputs"]["mask"].as_str().unwrap_or("?"),
            );
            Ok((report, text))
        }
    }
}
