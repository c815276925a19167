"""Fixes the pinned simulators need on Python 3.11 offline; idempotent (run by sim/setup.sh after pip).

1. safety-gymnasium 1.0.0 declares dataclass fields `color: np.array = COLOR[...]`; Python 3.11 rejects mutable
   defaults, so `import safety_gymnasium` fails. Rewrite them to `field(default_factory=lambda: COLOR[...])`
   (the objects get the same shared array as before, so behaviour is unchanged).
2. metadrive-simulator 0.4.3 ships no assets and downloads them on first use, which fails offline. Headless
   simulation loads no asset files; create the two files its "are the assets there?" check looks at.
"""
import importlib.metadata
import importlib.util
import re
import sys
from pathlib import Path

COLOR_FIELD = re.compile(r"^(\s+color: [^=]+= )(COLOR\[[^\]]+\])\s*$", re.MULTILINE)


def package_dir(name):
    spec = importlib.util.find_spec(name)
    if spec is None or spec.origin is None:
        sys.exit(f"{name} is not installed")
    return Path(spec.origin).parent


def fix_safety_gymnasium():
    root = package_dir("safety_gymnasium")
    changed = 0
    for path in sorted(root.rglob("*.py")):
        text = path.read_text()
        fixed, n = COLOR_FIELD.subn(r"\1field(default_factory=lambda: \2)", text)
        if n == 0:
            continue
        if not re.search(r"^from dataclasses import .*\bfield\b", fixed, re.MULTILINE):
            fixed, m = re.subn(r"^from dataclasses import dataclass\s*$", "from dataclasses import dataclass, field",
                               fixed, count=1, flags=re.MULTILINE)
            if m != 1:
                sys.exit(f"{path}: cannot add the `field` import")
        path.write_text(fixed)
        changed += n
    return changed


def fix_metadrive_assets():
    import metadrive

    assets = Path(metadrive.__file__).parent / "assets"
    version = assets / "version.txt"
    grass = assets / "textures" / "grass1" / "GroundGrassGreen002_COL_1K.jpg"
    grass.parent.mkdir(parents=True, exist_ok=True)
    version.write_text(importlib.metadata.version("metadrive-simulator"))
    grass.touch()


def main():
    # safety_gymnasium cannot be imported before the fix, so find it without importing it.
    fields = fix_safety_gymnasium()
    print(f"safety-gymnasium: {fields} dataclass fields fixed", file=sys.stderr)
    import safety_gymnasium  # noqa: F401  (now importable)
    fix_metadrive_assets()
    print("metadrive: offline asset check satisfied", file=sys.stderr)


if __name__ == "__main__":
    main()
