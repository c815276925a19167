//! The speed-ups the worker applies to Safety-Gymnasium's and Bullet-Safety-Gym's own Python
//! (`sim/python/dsrl_sim/speedups.py`) change no episode: `speedups.verify` steps every Safety-Gymnasium and
//! Bullet-Safety-Gym task of the catalog with and without them and compares the outputs, the layout each reset
//! draws, the whole physics state and the replaced readings (contact costs, lidar, body and link states), bit for
//! bit. Speed-ups that are off in the last bit of one coordinate or one lidar reading, draw another layout, miss a
//! contact or clip an action otherwise must be caught, so the comparison can fail.

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

/// `speedups.verify(task, steps, seed, episode_steps)` on every catalog task of `families` (`count` of them), each
/// crossing at least `resets` resets; fails the test on any difference.
fn verify_every_task(families: &[Family], count: usize, steps: u32, seed: u32, episode_steps: u32, resets: u32) {
    let catalog = Catalog::embedded().unwrap();
    let tasks: Vec<String> = catalog
        .tasks()
        .iter()
        .filter(|t| families.contains(&t.family))
        .map(|t| format!("'{}'", t.simulator_env_id))
        .collect();
    assert_eq!(tasks.len(), count);
    let (ok, out) = simulator_python(&format!(
        "from dsrl_sim import speedups\n\
         for task in [{}]:\n    \
             print(task, *speedups.verify(task, {steps}, seed={seed}, episode_steps={episode_steps}))\n",
        tasks.join(", ")
    ));
    assert!(ok, "the speed-ups changed an episode:\n{out}");
    // (An episode may also end early, when its agent falls or leaves the bounds: more episodes, never fewer.)
    let checked = out
        .lines()
        .filter(|l| {
            let fields: Vec<&str> = l.split(' ').collect();
            fields.len() == 4 && fields[1] == steps.to_string() && fields[2].parse::<u32>().is_ok_and(|e| e >= resets)
        })
        .count();
    assert_eq!(checked, count, "{out}");
}

#[test]
fn the_speedups_leave_every_safety_gymnasium_task_bit_identical() {
    // Episodes cut after 40 steps: at least five resets a task, each drawing a layout (the Button tasks' draw the
    // most).
    verify_every_task(
        &[Family::SafetyGymNavigation, Family::SafetyGymVelocity],
        21,
        200,
        7,
        40,
        5,
    );
    // Whole Button episodes too: the gremlins move at every substep, and the cached mocap rows follow the model
    // rebuilt at the reset after a full episode.
    let (ok, out) = simulator_python(
        "from dsrl_sim import speedups\n\
         for task in ['SafetyPointButton2-v0', 'SafetyCarButton1-v0']:\n    \
             print(task, *speedups.verify(task, 1100, seed=3))\n",
    );
    assert!(ok, "the speed-ups changed an episode:\n{out}");
    assert_eq!(
        out.lines().filter(|l| l.split(' ').nth(1) == Some("1100")).count(),
        2,
        "{out}"
    );
    // Episodes that run into the obstacles: these (task, seed) pairs touch pillars, vases, gremlins and buttons
    // (the test below shows that each pair's contacts reach its cost).
    let (ok, out) = simulator_python(&format!(
        "from dsrl_sim import speedups\n\
         for task, seed, _ in [{CONTACTS}]:\n    \
             print(task, *speedups.verify(task, 1200, seed=seed, episode_steps=300))\n"
    ));
    assert!(ok, "the speed-ups changed an episode:\n{out}");
    assert_eq!(
        out.lines().filter(|l| l.split(' ').nth(1) == Some("1200")).count(),
        4,
        "{out}"
    );
}

/// (simulator id, seed, geom prefix): `verify(id, 1200, seed=seed, episode_steps=300)` has the agent touch a geom
/// whose name starts with the prefix.
const CONTACTS: &str = "('SafetyPointPush2-v0', 0, 'pillar'), ('SafetyCarGoal2-v0', 1, 'vase'), \
                        ('SafetyPointButton1-v0', 0, 'gremlin'), ('SafetyCarButton2-v0', 1, 'button')";

#[test]
fn speedups_off_in_one_bit_a_layout_or_a_contact_are_caught() {
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

    // A lidar reading one ulp off: caught in float64, where `verify` compares the lidar itself (an observation is
    // float32 and would mostly hide it).
    let (ok, out) = simulator_python(
        "from dsrl_sim import speedups\n\
         lidar = speedups._fast_lidar_pseudo\n\
         speedups._fast_lidar_pseudo = lambda task, positions: lidar(task, positions) * (1 + 2**-52)\n\
         speedups.verify('SafetyPointGoal1-v0', 50)\n",
    );
    assert!(!ok, "a lidar reading one ulp off went unnoticed:\n{out}");
    assert!(
        out.contains("AssertionError: SafetyPointGoal1-v0: episode 0 step 0 goal lidar"),
        "{out}"
    );

    // Contacts not counted: caught in each (task, seed) pair above, once per kind of obstacle, so those runs do
    // touch every kind (in the step's cost, or first in the obstacle's own cost, which `verify` compares too: the
    // tasks report costs as indicators, which hide a count that is off but not zero).
    let (ok, out) = simulator_python(&format!(
        "from dsrl_sim import speedups\n\
         count = speedups._agent_contacts\n\
         for task, seed, missed in [{CONTACTS}]:\n    \
             speedups._agent_contacts = lambda obj, prefix, exclude=None: \
         0 if prefix == missed else count(obj, prefix, exclude)\n    \
             try:\n        \
                 speedups.verify(task, 1200, seed=seed, episode_steps=300)\n        \
                 print(task, missed, 'not caught')\n    \
             except AssertionError as e:\n        \
                 print(task, missed, 'caught:', str(e)[:100])\n"
    ));
    assert!(ok, "{out}");
    let caught = out
        .lines()
        .filter(|l| l.contains(" caught: ") && l.contains("cost: the speed-ups give"))
        .count();
    assert_eq!(caught, 4, "missed contacts went unnoticed:\n{out}");
}

#[test]
fn the_speedups_leave_every_bullet_safety_gym_task_bit_identical() {
    // Episodes cut after 100 steps: several resets a task, and the Drone and Ant agents fall or leave the bounds
    // within them on some seeds (an early end), which the outputs compare too.
    verify_every_task(&[Family::Bullet], 8, 400, 5, 100, 4);
}

/// Runs `verify` on `task` with the speed-up `fast` (a `_fast_*_state` of speedups.py) giving a state whose
/// `index`-th coordinate is one ulp larger; -> (exit success, output).
fn state_one_ulp_off(fast: &str, index: usize, task: &str) -> (bool, String) {
    simulator_python(&format!(
        "import numpy as np\n\
         from dsrl_sim import speedups\n\
         state = speedups.{fast}\n\
         def off_by_one_ulp(self):\n    \
             s = state(self)\n    \
             s[{index}] = np.nextafter(s[{index}], np.inf)\n    \
             return s\n\
         speedups.{fast} = off_by_one_ulp\n\
         speedups.verify('{task}', 50)\n"
    ))
}

#[test]
fn bullet_speedups_off_in_one_bit_or_clipping_otherwise_are_caught() {
    // A body state one ulp off in its last coordinate (the angular velocity's z, which the Ball's observation
    // scales by 0.1).
    let (ok, out) = state_one_ulp_off("_fast_body_state", 11, "SafetyBallCircle-v0");
    assert!(!ok, "a body state one ulp off went unnoticed:\n{out}");
    assert!(
        out.contains("AssertionError: SafetyBallCircle-v0: reset 0")
            || out.contains("AssertionError: SafetyBallCircle-v0: episode 0 step 0"),
        "{out}"
    );

    // A link state one ulp off (the Car's and the Ant's observations read their links).
    let (ok, out) = state_one_ulp_off("_fast_link_state", 0, "SafetyCarRun-v0");
    assert!(!ok, "a link state one ulp off went unnoticed:\n{out}");
    assert!(out.contains("AssertionError: SafetyCarRun-v0: "), "{out}");

    // Actions clipped into (-0.999, 0.999) instead of [-1, 1]: `verify`'s actions reach the bounds.
    let (ok, out) = simulator_python(
        "import numpy as np\n\
         from dsrl_sim import speedups\n\
         speedups._fast_agent_clip = lambda self, action: np.clip(action, -0.999, 0.999)\n\
         speedups.verify('SafetyBallRun-v0', 200)\n",
    );
    assert!(!ok, "actions clipped otherwise went unnoticed:\n{out}");
    assert!(
        out.contains("AssertionError: SafetyBallRun-v0: episode 0 step"),
        "{out}"
    );

    // A client that keeps its functions past `disconnect`: they would call a simulation that is gone (or, once
    // its id is reused, another env's).
    let close = "import functools\n\
                 from dsrl_sim import tasks\n\
                 env = tasks.make_env('SafetyBallRun-v0')\n\
                 env.reset(0)\n\
                 env.step([0.5, 0.5])\n\
                 client = env._env.unwrapped.bc\n\
                 assert isinstance(vars(client).get('stepSimulation'), functools.partial), vars(client)\n\
                 env.close()\n\
                 kept = [k for k, v in vars(client).items() if isinstance(v, functools.partial)]\n\
                 assert not kept, f'kept past disconnect: {kept}'\n";
    let (ok, out) = simulator_python(close);
    assert!(ok, "{out}");
    let (ok, out) = simulator_python(&format!(
        "from dsrl_sim import speedups\n\
         lookup = speedups._library\n\
         speedups._fast_client_getattr = lambda self, name: self.__dict__.setdefault(name, \
         lookup('BulletClient.__getattr__')(self, name))\n\
         {close}"
    ));
    assert!(!ok, "functions kept past disconnect went unnoticed:\n{out}");
    assert!(out.contains("kept past disconnect"), "{out}");
}
