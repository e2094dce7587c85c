//! The campaign on a real Slurm (issue 22): the test starts a one-node cluster on this machine
//! — `munged`, `slurmctld` and `slurmd` with a generated `slurm.conf` for localhost (2 CPUs,
//! no cgroups: `proctrack/linuxproc`, `task/none`), everything in a temporary folder, ports
//! 16917/16918 — submits a campaign of four simulated survey lines that cross each other with
//! `fwlidar campaign submit --merge-nodes 2`, waits for the array, the two group merges and the
//! merge job, and compares the mosaic
//! with one `fwlidar replay` of the four lines in sequence byte for byte (but the tiles' resume
//! records, whose watermarks say when a tile closed). Then it cancels one array
//! task of a second submission (the killed task), sees the merge job never start, resubmits,
//! and gets the same bytes. The daemons are stopped when the test ends, however it ends.
//!
//! Needs the Slurm daemons (`tests/run.sh` installs `slurm-wlm` and `munge`) and root; without
//! them it fails, saying so.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

/// The cluster's daemons; stopped on drop.
struct Cluster {
    dir: PathBuf,
    conf: PathBuf,
}

impl Drop for Cluster {
    fn drop(&mut self) {
        for pid in ["slurmd.pid", "slurmctld.pid", "munged.pid"] {
            if let Ok(p) = std::fs::read_to_string(self.dir.join("run").join(pid))
                && let Ok(p) = p.trim().parse::<i32>()
            {
                // SAFETY: kill(2) on a pid our own daemons wrote; no memory is involved.
                unsafe {
                    libc::kill(p, libc::SIGTERM);
                }
            }
        }
        std::thread::sleep(Duration::from_millis(500));
    }
}

/// A Slurm or munge program by its full path (daemons live in /usr/sbin, which a user's PATH
/// may lack); a missing one fails the test, naming `tests/run.sh`.
fn program(cmd: &str) -> Command {
    let package = if cmd == "munged" {
        "munge"
    } else {
        "slurm-wlm"
    };
    Command::new(common::tool(
        cmd,
        package,
        "this check runs a one-node Slurm cluster",
    ))
}

/// This machine's short host name (slurmd finds its node by it).
fn hostname() -> String {
    let mut buf = [0u8; 256];
    // SAFETY: the buffer is valid for its length; gethostname NUL-terminates within it.
    let r = unsafe { libc::gethostname(buf.as_mut_ptr().cast(), buf.len()) };
    assert_eq!(r, 0, "gethostname failed");
    let end = buf.iter().position(|&b| b == 0).unwrap_or(buf.len());
    let name = String::from_utf8_lossy(&buf[..end]).to_string();
    name.split('.').next().unwrap_or_default().to_string()
}

fn start(dir: &Path) -> Cluster {
    for d in ["state", "spool", "run", "log"] {
        std::fs::create_dir_all(dir.join(d)).unwrap();
    }
    let key = dir.join("munge.key");
    let bytes: Vec<u8> = (0..1024u32)
        .map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8)
        .collect();
    std::fs::write(&key, bytes).unwrap();
    let mut perm = std::fs::metadata(&key).unwrap().permissions();
    std::os::unix::fs::PermissionsExt::set_mode(&mut perm, 0o400);
    std::fs::set_permissions(&key, perm).unwrap();
    let d = dir.display();
    let host = hostname();
    // The node's memory as Slurm checks `--mem` against it: what this machine has, less 512 MB.
    let mem = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|m| {
            m.lines()
                .find(|l| l.starts_with("MemTotal:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|kb| kb.parse::<u64>().ok())
        })
        .map_or(4096, |kb| (kb / 1024).saturating_sub(512).max(2048));
    let conf = dir.join("slurm.conf");
    std::fs::write(
        &conf,
        format!(
            "ClusterName=fwlidar-test\nSlurmctldHost={host}(127.0.0.1)\nSlurmUser=root\n\
             SlurmdUser=root\nAuthType=auth/munge\nAuthInfo=socket={d}/run/munge.sock\n\
             CryptoType=crypto/munge\nSlurmctldPort=16917\nSlurmdPort=16918\n\
             StateSaveLocation={d}/state\nSlurmdSpoolDir={d}/spool\n\
             SlurmctldPidFile={d}/run/slurmctld.pid\nSlurmdPidFile={d}/run/slurmd.pid\n\
             SlurmctldLogFile={d}/log/slurmctld.log\nSlurmdLogFile={d}/log/slurmd.log\n\
             ProctrackType=proctrack/linuxproc\nTaskPlugin=task/none\n\
             JobAcctGatherType=jobacct_gather/none\nAccountingStorageType=accounting_storage/none\n\
             JobCompType=jobcomp/none\nMpiDefault=none\nSchedulerType=sched/backfill\n\
             SelectType=select/cons_tres\nSelectTypeParameters=CR_CPU\nReturnToService=2\n\
             NodeName={host} NodeAddr=127.0.0.1 CPUs=2 RealMemory={mem} State=UNKNOWN\n\
             PartitionName=debug Nodes=ALL Default=YES MaxTime=INFINITE State=UP\n"
        ),
    )
    .unwrap();
    let cluster = Cluster {
        dir: dir.to_path_buf(),
        conf: conf.clone(),
    };
    let run = |cmd: &str, args: &[String]| {
        let o = program(cmd)
            .args(args)
            .env("SLURM_CONF", &conf)
            .output()
            .unwrap();
        assert!(
            o.status.success(),
            "{cmd}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
    };
    run(
        "munged",
        &[
            "--force".into(),
            format!("--key-file={d}/munge.key"),
            format!("--socket={d}/run/munge.sock"),
            format!("--pid-file={d}/run/munged.pid"),
            format!("--log-file={d}/log/munged.log"),
            format!("--seed-file={d}/run/munge.seed"),
        ],
    );
    run("slurmctld", &["-f".into(), conf.display().to_string()]);
    run("slurmd", &["-f".into(), conf.display().to_string()]);
    // The node is up when sinfo calls it idle.
    let t = Instant::now();
    loop {
        let o = program("sinfo")
            .args(["-h", "-o", "%t"])
            .env("SLURM_CONF", &conf)
            .output()
            .unwrap();
        if String::from_utf8_lossy(&o.stdout).contains("idle") {
            break;
        }
        assert!(
            t.elapsed() < Duration::from_secs(60),
            "the one-node cluster did not come up: {}",
            std::fs::read_to_string(dir.join("log/slurmctld.log")).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(300));
    }
    cluster
}

fn slurm(c: &Cluster, cmd: &str, args: &[&str]) -> String {
    let o = program(cmd)
        .args(args)
        .env("SLURM_CONF", &c.conf)
        .output()
        .unwrap();
    String::from_utf8_lossy(&o.stdout).to_string()
}

/// Waits until none of `jobs` is queued or running.
fn wait(c: &Cluster, jobs: &[String]) {
    let t = Instant::now();
    loop {
        let q = slurm(
            c,
            "squeue",
            &["-h", "-o", "%i %T %r", "-j", &jobs.join(",")],
        );
        if q.trim().is_empty() {
            return;
        }
        assert!(
            t.elapsed() < Duration::from_secs(600),
            "jobs still queued: {q}"
        );
        std::thread::sleep(Duration::from_millis(500));
    }
}

fn submit(c: &Cluster, file: &Path, extra: &[&str]) -> Vec<String> {
    let o = Command::new(env!("CARGO_BIN_EXE_fwlidar"))
        .args([
            "campaign",
            "submit",
            file.to_str().unwrap(),
            "--cpus",
            "2",
            "--time",
            "00:10:00",
        ])
        .args(extra)
        .env("SLURM_CONF", &c.conf)
        .output()
        .unwrap();
    let out = common::text(&o.stdout);
    assert!(o.status.success(), "{out}{}", common::text(&o.stderr));
    out.lines()
        .find_map(|l| l.strip_prefix("jobs "))
        .unwrap()
        .split(", ")
        .map(str::to_string)
        .collect()
}

#[test]
fn a_campaign_on_a_one_node_slurm_gives_a_sequential_replays_bytes_even_after_a_killed_task() {
    for cmd in [
        "munged",
        "slurmctld",
        "slurmd",
        "sbatch",
        "squeue",
        "scancel",
        "sinfo",
    ] {
        let package = if cmd == "munged" {
            "munge"
        } else {
            "slurm-wlm"
        };
        common::tool(cmd, package, "this check runs a one-node Slurm cluster");
    }
    // SAFETY: geteuid has no preconditions.
    assert!(
        unsafe { libc::geteuid() } == 0,
        "the one-node Slurm of this check runs its daemons as root: run `{}` as root",
        common::SETUP
    );
    let dir = tempfile::tempdir().unwrap();
    let cluster = start(&dir.path().join("slurm"));
    // Four crossing lines, as tests/campaign.rs makes them.
    let work = dir.path().join("work");
    common::crossing_lines(&work);
    let file = |name: &str, out: &str| common::crossing_campaign(&work, name, out);
    // On Slurm: the array of four lines, the array of two group merges after it (the merge
    // spread over two nodes), and the last merge after that.
    let on_slurm = file("slurm.toml", "out_slurm");
    let jobs = submit(&cluster, &on_slurm, &["--merge-nodes", "2"]);
    assert_eq!(jobs.len(), 3, "{jobs:?}");
    wait(&cluster, &jobs);
    let report: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(work.join("out_slurm/campaign.json")).unwrap_or_else(|e| {
            panic!(
                "no campaign.json ({e}); merge log: {}",
                std::fs::read_to_string(work.join("out_slurm/slurm/merge.log")).unwrap_or_default()
            )
        }),
    )
    .unwrap();
    assert_eq!(report["lines"].as_array().unwrap().len(), 4);
    assert_eq!(report["merge"]["groups"], 2, "{report}");
    assert_eq!(report["merge"]["groups_merged_here"], 0, "{report}");
    // The reference: one replay of the four lines in sequence, with the campaign's run.toml.
    let seq = common::sequential_replay(&work, &work.join("out_slurm/run.toml"), &work.join("seq"));
    common::assert_same_store_but_watermarks(&work.join("out_slurm/mosaic.zarr"), &seq);
    assert!(work.join("out_slurm/rasters/chm.vrt").is_file());
    let reference = common::file_tree(&work.join("out_slurm/mosaic.zarr"));
    // A killed array task: cancel line 3's task of a new submission before it runs (the node
    // runs one 2-CPU task at a time), so the merge job's dependency can never be met.
    let killed = file("killed.toml", "out_killed");
    let jobs = submit(&cluster, &killed, &[]);
    let cancelled = slurm(&cluster, "scancel", &[&format!("{}_3", jobs[0])]);
    let _ = cancelled;
    wait(&cluster, &jobs[..1]);
    assert!(!work.join("out_killed/lines/line3/done.json").exists());
    assert!(!work.join("out_killed/mosaic.zarr").exists());
    let _ = slurm(&cluster, "scancel", &[&jobs[1]]);
    wait(&cluster, &jobs[1..]);
    // Resubmitting runs the missing line alone, then the merge: the same bytes.
    let again = submit(&cluster, &killed, &[]);
    let script = std::fs::read_to_string(work.join("out_killed/slurm/lines.sbatch")).unwrap();
    assert!(script.contains("#SBATCH --array=3\n"), "{script}");
    wait(&cluster, &again);
    assert!(
        common::file_tree(&work.join("out_killed/mosaic.zarr")) == reference,
        "the mosaic after the killed task's resubmission differs"
    );
}
