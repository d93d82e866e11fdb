"""README.md keeps its promises: the two commands in its first 40 lines, at most 250 lines, and its library example
runs as written (three steps instead of the budget's)."""

import os
import re

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _readme() -> str:
    return open(os.path.join(REPO, "README.md")).read()


def test_the_two_commands_are_in_the_first_40_lines():
    head = "\n".join(_readme().splitlines()[:40])
    assert "bash scripts/setup.sh && python bin/train.py --config=configs/demo.py" in head
    assert "bash scripts/setup.sh && python -m pytest -q" in head
    assert len(_readme().splitlines()) <= 250


def test_the_library_example_runs():
    code = re.search(r"```python\n(.*?)```", _readme(), re.S).group(1)
    code = code.replace("range(config.train.steps)", "range(3)")
    code = code.replace('make_sequence(config.data.synthetic)',
                        'make_sequence({"num_scans": 3, "num_beams": 8, "num_columns": 64, "gt_map_points": 0, '
                        '"scene_size_m": 30.0, "trajectory_radius_m": 5.0, "max_range_m": 30.0})')
    assert code.count("range(3)") == 1 and "num_scans" in code  # the example still has the lines replaced
    scope = {}
    exec(compile(code, "README.md", "exec"), scope)
    assert scope["T_refined"].shape == (3, 4, 4) and int(scope["state"].step) == 3
