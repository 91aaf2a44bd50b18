//! `lungdyn instances`: the running lungdyn instances — what `lungdyn scene event INSTANCE …` needs —
//! with each one's processes, its scene and how long it has run.

use serde::Serialize;
use transport::{Instance, RunningInstance};

/// Options of `lungdyn instances`.
#[derive(Debug, Clone, clap::Args)]
pub struct InstancesArgs {
    /// Print one JSON object (`instances`: name, scene, age_s, processes) on stdout.
    #[arg(long)]
    pub json: bool,
}

/// One process of an instance.
#[derive(Debug, Serialize)]
pub struct ProcessRow {
    /// Role.
    pub role: String,
    /// Pid.
    pub pid: u32,
}

/// One running instance.
#[derive(Debug, Serialize)]
pub struct InstanceRow {
    /// Its name: what `scene event` takes.
    pub name: String,
    /// The scene it runs: the launcher's `--scene`, else the engine's, else the built-in default.
    pub scene: String,
    /// Seconds since its first process started.
    pub age_s: u64,
    /// Its live processes.
    pub processes: Vec<ProcessRow>,
}

/// The instances.
#[derive(Debug, Serialize)]
pub struct Instances {
    /// Running instances, by name.
    pub instances: Vec<InstanceRow>,
}

/// The value of `--scene` in a recorded command line (`--scene X` or `--scene=X`).
fn scene_arg(cmdline: &str) -> Option<String> {
    let mut words = cmdline.split(' ');
    while let Some(w) = words.next() {
        if w == "--scene" {
            return words.next().map(str::to_string);
        }
        if let Some(v) = w.strip_prefix("--scene=") {
            return Some(v.to_string());
        }
    }
    None
}

fn row(r: &RunningInstance, now_s: u64) -> InstanceRow {
    let scene = ["launcher", "engine"]
        .iter()
        .filter_map(|role| r.process(role))
        .find_map(|p| scene_arg(&p.cmdline))
        .unwrap_or_else(|| "built-in default".to_string());
    let first = r
        .processes
        .iter()
        .map(|p| p.since_unix_s)
        .min()
        .unwrap_or(now_s);
    InstanceRow {
        name: r.name.clone(),
        scene,
        age_s: now_s.saturating_sub(first),
        processes: r
            .processes
            .iter()
            .map(|p| ProcessRow {
                role: p.role.clone(),
                pid: p.pid,
            })
            .collect(),
    }
}

/// The running instances.
pub fn list() -> Instances {
    let now_s = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    Instances {
        instances: Instance::running().iter().map(|r| row(r, now_s)).collect(),
    }
}

/// The table a person reads.
pub fn text(list: &Instances) -> String {
    if list.instances.is_empty() {
        return "no lungdyn instance is running (start one with `lungdyn demo [--scene FILE] \
                [--instance NAME]`)\n"
            .to_string();
    }
    let mut s = format!(
        "{:<24} {:>8}  {:<46} scene\n",
        "instance", "running", "processes (pid)"
    );
    for i in &list.instances {
        let procs = i
            .processes
            .iter()
            .map(|p| format!("{} {}", p.role, p.pid))
            .collect::<Vec<_>>()
            .join(", ");
        s += &format!(
            "{:<24} {:>6} s  {:<46} {}\n",
            i.name, i.age_s, procs, i.scene
        );
    }
    s += "send an intervention with `lungdyn scene event INSTANCE needle-decompression --side left`\n";
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_scene_comes_from_either_form_of_the_flag() {
        assert_eq!(
            scene_arg("lungdyn demo --scene scenes/a.toml --seconds 5").as_deref(),
            Some("scenes/a.toml")
        );
        assert_eq!(
            scene_arg("engine --scene=/x/scene.resolved.toml").as_deref(),
            Some("/x/scene.resolved.toml")
        );
        assert_eq!(scene_arg("lungdyn demo --seconds 5"), None);
        assert_eq!(scene_arg("lungdyn demo --scene"), None);
    }

    #[test]
    fn a_held_engine_lock_is_listed_with_its_instance() {
        let name = format!("inst-list-{}", std::process::id());
        let i = Instance::new(&name).unwrap();
        let _held = i.lock("engine").unwrap();
        let l = list();
        let me = l.instances.iter().find(|r| r.name == name).expect("listed");
        assert_eq!(me.processes.len(), 1);
        assert_eq!(me.processes[0].role, "engine");
        assert!(text(&l).contains(&name));
    }
}
