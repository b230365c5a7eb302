#!/usr/bin/env python3
"""Write a synthetic shadecap dataset with ground truth (docs/dataset-format.md).

    python scripts/make_synthetic.py --out data/demo                          # the README demo scene
    python scripts/make_synthetic.py --config small --model lambert --out /tmp/s
    python scripts/make_synthetic.py --mesh torus --views 24 --size 128 --noise 1000 --read-noise 0.002 \\
        --encoding srgb --out /tmp/torus_png

The same as `shadecap synth` (one parser, every option in both); `--help` lists every option.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from capture.cli import script_main  # noqa: E402


def main(argv=None) -> int:
    return script_main("synth", Path(__file__).name, argv)


if __name__ == "__main__":
    sys.exit(main())
