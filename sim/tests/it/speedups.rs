//! The speed-ups the worker applies to the simulators' own Python (`sim/python/dsrl_sim/speedups.py`) change no
//! episode: `speedups.verify` steps each Button task (the tasks with gremlins) with and without them and compares
//! every output and the whole physics state bit for bit. A speed-up that is off in the last bit of one coordinate
//! must be caught, so the comparison can fail.

use std::path::PathBuf;
use std::process::Command;

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
fn the_speedups_leave_every_button_task_bit_identical() {
    let (ok, out) = simulator_python(
        "from dsrl_sim import speedups\n\
         for task in ['SafetyPointButton1-v0', 'SafetyPointButton2-v0', 'SafetyCarButton1-v0', \
         'SafetyCarButton2-v0']:\n    \
             steps, episodes = speedups.verify(task, 1100, seed=7)\n    \
             print(task, steps, episodes)\n",
    );
    assert!(ok, "the speed-ups changed an episode:\n{out}");
    // 1,100 steps cross an episode's end (1,000 steps), so the cached mocap rows are rebuilt with the model.
    assert_eq!(out.lines().filter(|l| l.ends_with(" 1100 2")).count(), 4, "{out}");
}

#[test]
fn a_speedup_off_in_the_last_bit_is_caught() {
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
}
