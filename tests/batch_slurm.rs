//! A manifest of three generated scans (one broken) through a real
//! single-node Slurm cluster: `batch --sbatch` writes the job array script,
//! `sbatch --wait` runs it, two scans finish and the broken one reports its
//! error; resubmitting the same script redoes nothing that finished; the
//! merged dataset loads in pyarrow, polars and `datasets` where Python has
//! them. Skips with a message where Slurm and munge cannot be had
//! (`tests/slurm/setup.sh` says why; `.ci/run` installs them with apt).

mod common;

use common::batch::{batch, python_loads, stamp, status, three_scans};
use common::{s, stderr};
use std::path::{Path, PathBuf};
use std::process::Command;

/// Stops the cluster's daemons when the test ends, however it ends.
struct Cluster(PathBuf);

impl Drop for Cluster {
    fn drop(&mut self) {
        let _ = Command::new("bash")
            .arg(slurm_script("teardown.sh"))
            .arg(&self.0)
            .status();
    }
}

fn slurm_script(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/slurm").join(name)
}

/// Start the cluster in `dir`, or `None` (with the reason printed) when it cannot be had.
fn start_cluster(dir: &Path) -> Option<Cluster> {
    let o = Command::new("bash").arg(slurm_script("setup.sh")).arg(dir).output();
    let o = match o {
        Ok(o) => o,
        Err(e) => {
            eprintln!("skipped: cannot run bash ({e})");
            return None;
        }
    };
    let cluster = Cluster(dir.to_path_buf());
    if !o.status.success() {
        eprintln!("skipped: {}", stderr(&o).trim());
        return None;
    }
    Some(cluster)
}

fn sbatch_wait(conf: &Path, script: &Path, cwd: &Path) -> std::process::Output {
    Command::new("sbatch")
        .arg("--wait")
        .arg(script)
        .env("SLURM_CONF", conf)
        .env_remove("SLURM_ARRAY_TASK_ID")
        .env_remove("JOB_COMPLETION_INDEX")
        .current_dir(cwd)
        .output()
        .unwrap()
}

#[test]
fn a_manifest_of_three_scans_runs_as_a_slurm_job_array() {
    let dir = tempfile::tempdir().unwrap();
    let Some(cluster) = start_cluster(&dir.path().join("cluster")) else {
        return;
    };
    let conf = cluster.0.join("slurm.conf");
    let work = dir.path().join("work");
    std::fs::create_dir_all(&work).unwrap();
    let (manifest, [a, b, c]) = three_scans(&work, r#""steps": 150"#);

    // The script: one task a line, 1 CPU each (the test machine may have 2).
    let o = batch(
        &manifest,
        &["--sbatch", "--cpus", "1", "--mem", "2G", "--time-limit", "0:30:00"],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let script_text = String::from_utf8(o.stdout).unwrap();
    for line in [
        "#SBATCH --array=0-2%3",
        "#SBATCH --cpus-per-task=1",
        "#SBATCH --mem=2048M",
        "#SBATCH --time=0-00:30:00",
    ] {
        assert!(script_text.contains(line), "{line} in\n{script_text}");
    }
    let script = work.join("job.sh");
    std::fs::write(&script, &script_text).unwrap();

    let o = sbatch_wait(&conf, &script, &work);
    assert!(
        !o.status.success(),
        "the broken scan's task fails, so the array does: {}",
        stderr(&o)
    );
    for scan in [&a, &b] {
        let st = status(scan);
        assert_eq!(st["state"], "done", "{st}");
        assert!(st["slurm_job"].as_str().is_some_and(|j| j.contains('_')), "{st}");
    }
    let st = status(&c);
    assert_eq!(st["state"], "failed", "{st}");
    assert!(st["error"].as_str().unwrap().contains("000002.png"), "{st}");
    // Each task's log is where the script said; the broken one's names the problem.
    let logs: Vec<String> = std::fs::read_dir(work.join("slurm-logs"))
        .unwrap()
        .map(|e| std::fs::read_to_string(e.unwrap().path()).unwrap())
        .collect();
    assert_eq!(logs.len(), 3);
    assert!(logs
        .iter()
        .any(|l| l.contains("scan broken") && l.contains("000002.png")));

    // The same array again: the finished scans are not redone.
    let (a_done, b_done) = (stamp(&a), stamp(&b));
    let o = sbatch_wait(&conf, &script, &work);
    assert!(!o.status.success());
    assert!(stamp(&a) == a_done && stamp(&b) == b_done, "finished scans were redone");
    assert_eq!(status(&a)["fit"]["runs"], 1);

    let out = work.join("dataset");
    let o = batch(&manifest, &["--merge", s(&out)]);
    assert!(o.status.success(), "{}", stderr(&o));
    let summary = std::fs::read_to_string(out.join("summary.csv")).unwrap();
    assert!(summary.contains("broken,") && summary.contains(",failed,"), "{summary}");
    python_loads(&out, &["a", "b"]);
}
