//! `cargo xtask plot-runs`: learning curves of one or more training runs in one SVG/PNG — the
//! training loss (the trainer's running average, `loss_avg` of `train.csv`) above a validation
//! column of `val.csv`, against the iteration — e.g. a run from scratch against a fine-tune.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};

#[derive(clap::Args)]
pub struct PlotRunsArgs {
    /// A run as NAME=PATH: PATH a run folder (`train.csv`, `val.csv`, as `train-pose` and
    /// `train-seg` write) or a file prefix (`models/pose-cpu-ot` for
    /// `models/pose-cpu-ot.train.csv` and `.val.csv`). Repeat for more runs.
    #[arg(long = "run", required = true)]
    pub runs: Vec<String>,
    /// The `val.csv` column to draw (e.g. `rotation_acc_15`, `rotation_acc_15_sym`,
    /// `target_found_rate`); default: `rotation_acc_15_sym` where every run has it, else
    /// `rotation_acc_15`.
    #[arg(long)]
    pub metric: Option<String>,
    /// Title of the plot.
    #[arg(long, default_value = "Learning curves")]
    pub title: String,
    /// Output file (.svg or .png).
    #[arg(long)]
    pub out: PathBuf,
}

/// A numeric CSV as the trainers write it: a header, then rows of numbers. A row that is not
/// all numbers (a header written again by a resumed run) is skipped; a row whose iteration
/// repeats an earlier one (a run resumed from an older checkpoint) replaces the rows from it on.
#[derive(Debug)]
pub struct Table {
    pub columns: Vec<String>,
    pub rows: Vec<Vec<f64>>,
}

impl Table {
    pub fn read(path: &Path) -> Result<Table> {
        let mut reader = csv::ReaderBuilder::new()
            .flexible(true)
            .from_path(path)
            .with_context(|| format!("{}: cannot be read", path.display()))?;
        let columns: Vec<String> = reader
            .headers()
            .with_context(|| format!("{}: no header", path.display()))?
            .iter()
            .map(str::to_owned)
            .collect();
        if columns.first().map(String::as_str) != Some("iteration") {
            bail!("{}: the first column must be `iteration`", path.display());
        }
        let mut rows: Vec<Vec<f64>> = Vec::new();
        for (i, record) in reader.records().enumerate() {
            let record = record.with_context(|| format!("{}: row {}", path.display(), i + 2))?;
            let Ok(row) = record
                .iter()
                .map(|f| f.trim().parse::<f64>())
                .collect::<Result<Vec<f64>, _>>()
            else {
                continue;
            };
            if row.len() != columns.len() {
                bail!(
                    "{}: row {} has {} fields, the header {}",
                    path.display(),
                    i + 2,
                    row.len(),
                    columns.len()
                );
            }
            // A resumed run starts again after its checkpoint's iteration.
            while rows.last().is_some_and(|last| last[0] >= row[0]) {
                rows.pop();
            }
            rows.push(row);
        }
        Ok(Table { columns, rows })
    }

    /// (iteration, value) of `column`, or an error naming the columns there are.
    pub fn series(&self, column: &str, path: &Path) -> Result<Vec<(f64, f64)>> {
        let Some(c) = self.columns.iter().position(|n| n == column) else {
            bail!(
                "{}: no column `{column}` (columns: {})",
                path.display(),
                self.columns.join(", ")
            );
        };
        Ok(self.rows.iter().map(|r| (r[0], r[c])).collect())
    }
}

/// The `train.csv` and `val.csv` of a run given as a folder or a file prefix.
fn run_files(path: &Path) -> (PathBuf, PathBuf) {
    if path.is_dir() {
        (path.join("train.csv"), path.join("val.csv"))
    } else {
        let with = |ext: &str| {
            let mut p = path.as_os_str().to_owned();
            p.push(ext);
            PathBuf::from(p)
        };
        (with(".train.csv"), with(".val.csv"))
    }
}

pub fn run(args: PlotRunsArgs) -> Result<()> {
    let mut runs = Vec::new();
    for spec in &args.runs {
        let Some((name, path)) = spec.split_once('=') else {
            bail!("--run {spec}: expected NAME=PATH");
        };
        let (train_path, val_path) = run_files(Path::new(path));
        let train = Table::read(&train_path)?;
        let val = Table::read(&val_path)?;
        runs.push((name.to_owned(), train_path, train, val_path, val));
    }
    let metric = match &args.metric {
        Some(m) => m.clone(),
        None if runs
            .iter()
            .all(|r| r.4.columns.iter().any(|c| c == "rotation_acc_15_sym")) =>
        {
            "rotation_acc_15_sym".into()
        }
        None => "rotation_acc_15".into(),
    };
    let mut top = Vec::new();
    let mut bottom = Vec::new();
    for (name, train_path, train, val_path, val) in &runs {
        top.push((name.clone(), train.series("loss_avg", train_path)?));
        bottom.push((name.clone(), val.series(&metric, val_path)?));
    }
    ic_geometry::io::create_parent_dir(&args.out)
        .with_context(|| format!("creating the folder of {}", args.out.display()))?;
    // ic_eval draws into a temporary file and renames it into place.
    ic_eval::plot_learning_curves(
        &args.out,
        &args.title,
        (
            "iteration",
            "training loss (running average)",
            &format!("validation {metric}"),
        ),
        &top,
        &bottom,
    )?;
    eprintln!("wrote {}", args.out.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_resumed_runs_repeated_header_and_replayed_iterations_are_dropped() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("val.csv");
        std::fs::write(
            &p,
            "iteration,acc\n500,0.1\n1000,0.2\n1500,0.9\niteration,acc\n1000,0.3\n1500,0.4\n",
        )
        .unwrap();
        let t = Table::read(&p).unwrap();
        assert_eq!(
            t.series("acc", &p).unwrap(),
            vec![(500.0, 0.1), (1000.0, 0.3), (1500.0, 0.4)]
        );
        let e = t.series("loss", &p).unwrap_err().to_string();
        assert!(e.contains("no column `loss`") && e.contains("acc"), "{e}");
    }

    #[test]
    fn plots_two_runs_given_as_a_folder_and_a_file_prefix() {
        let dir = tempfile::tempdir().unwrap();
        let a = dir.path().join("a");
        std::fs::create_dir(&a).unwrap();
        std::fs::write(a.join("train.csv"), "iteration,loss_avg\n1,9.0\n2,8.0\n").unwrap();
        std::fs::write(a.join("val.csv"), "iteration,rotation_acc_15\n2,0.2\n").unwrap();
        let b = dir.path().join("b");
        std::fs::write(
            dir.path().join("b.train.csv"),
            "iteration,loss_avg\n1,3.0\n",
        )
        .unwrap();
        std::fs::write(
            dir.path().join("b.val.csv"),
            "iteration,rotation_acc_15,rotation_acc_15_sym\n1,0.5,0.6\n",
        )
        .unwrap();
        let out = dir.path().join("plots/curves.svg");
        run(PlotRunsArgs {
            runs: vec![
                format!("scratch={}", a.display()),
                format!("fine-tune={}", b.display()),
            ],
            metric: None,
            title: "t".into(),
            out: out.clone(),
        })
        .unwrap();
        let svg = std::fs::read_to_string(&out).unwrap();
        // `a` has no symmetric column, so both draw rotation_acc_15.
        assert!(svg.contains("validation rotation_acc_15") && svg.contains("fine-tune"));
        let bad = run(PlotRunsArgs {
            runs: vec![format!("x={}", dir.path().join("missing").display())],
            metric: None,
            title: "t".into(),
            out,
        })
        .unwrap_err();
        assert!(format!("{bad:#}").contains("missing.train.csv"), "{bad:#}");
    }
}
