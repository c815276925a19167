//! The speed-ups the worker applies to Safety-Gymnasium's own Python (`sim/python/dsrl_sim/speedups.py`) change no
//! episode: `speedups.verify` steps every Safety-Gymnasium task of the catalog with and without them and compares
//! the outputs, the layout each reset draws and the whole physics state, bit for bit. Speed-ups that are off in the
//! last bit of one coordinate, or that draw another layout, must be caught, so the comparison can fail.

use std::path::PathBuf;
use std::process::Command;

use dsrl_suite::catalog::{Catalog, Family};

/// Runs `code` in the simulators' Python with `dsrl_sim` importable; -> (exit success, stdout + stderr).
fn simulator_python(code: &str) -> (bool, String) {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    let python = root.join(".venv-sim/bin/python");
    assert!(
        python.exists(),
        "no simulator environment at {} (run sim/setup.sh)",
        python.display()
    );
    let out = Command::new(python)
        .args(["-W", "ignore", "-c", code])
        .env("PYTHONPATH", root.join("sim/python"))
        .output()
        .expect("run the simulators' Python");
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.success(), text)
}

#[test]
fn the_speedups_leave_every_safety_gymnasium_task_bit_identical() {
    let catalog = Catalog::embedded().unwrap();
    let tasks: Vec<String> = catalog
        .tasks()
        .iter()
        .filter(|t| matches!(t.family, Family::SafetyGymNavigation | Family::SafetyGymVelocity))
        .map(|t| format!("'{}'", t.simulator_env_id))
        .collect();
    assert_eq!(tasks.len(), 21);
    // Episodes cut after 40 steps: at least five resets a task, each drawing a layout (the Button tasks' draw the most).
    let (ok, out) = simulator_python(&format!(
        "from dsrl_sim import speedups\n\
         for task in [{}]:\n    \
             steps, episodes = speedups.verify(task, 200, seed=7, episode_steps=40)\n    \
             print(task, steps, episodes)\n",
        tasks.join(", ")
    ));
    assert!(ok, "the speed-ups changed an episode:\n{out}");
    // (A velocity task's episode may also end early, when its agent falls: more episodes, never fewer.)
    let checked = out
        .lines()
        .filter(|l| {
            let fields: Vec<&str> = l.split(' ').collect();
            fields.len() == 3 && fields[1] == "200" && fields[2].parse::<u32>().is_ok_and(|e| e >= 5)
        })
        .count();
    assert_eq!(checked, 21, "{out}");
    // Whole Button episodes too: the gremlins move at every substep, and the cached mocap rows follow the model
    // rebuilt at the reset after a full episode.
    let (ok, out) = simulator_python(
        "from dsrl_sim import speedups\n\
         for task in ['SafetyPointButton2-v0', 'SafetyCarButton1-v0']:\n    \
             print(task, *speedups.verify(task, 1100, seed=3))\n",
    );
    assert!(ok, "the speed-ups changed an episode:\n{out}");
    assert_eq!(out.lines().filter(|l| l.ends_with(" 1100 2")).count(), 2, "{out}");
}

#[test]
fn speedups_off_in_the_last_bit_are_caught() {
    let (ok, out) = simulator_python(
        "from dsrl_sim import speedups\n\
         fast = speedups._fast_gremlins_move\n\
         def off_by_one_ulp(self):\n    \
             fast(self)\n    \
             self.engine.data.mocap_pos[:, 0] *= 1 + 2**-52\n\
         speedups._fast_gremlins_move = off_by_one_ulp\n\
         speedups.verify('SafetyPointButton1-v0', 50)\n",
    );
    assert!(!ok, "a gremlin position one ulp off went unnoticed:\n{out}");
    assert!(
        out.contains("AssertionError: SafetyPointButton1-v0: episode 0 step 0"),
        "{out}"
    );

    // A layout test that compares squared distances (no square root) decides some candidates otherwise.
    let (ok, out) = simulator_python(
        "import math\n\
         from dsrl_sim import speedups\n\
         speedups.math = type('squared', (), {'sqrt': staticmethod(lambda x: x)})\n\
         speedups.verify('SafetyPointGoal1-v0', 200, episode_steps=20)\n",
    );
    assert!(!ok, "a layout drawn with another distance went unnoticed:\n{out}");
    assert!(out.contains("AssertionError: SafetyPointGoal1-v0: reset"), "{out}");
}
