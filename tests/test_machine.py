import json
import os

import jax

from jaxslam._machine import cpu_model, machine_info


def test_machine_info_names_the_processor_and_is_json():
    info = machine_info()
    assert json.loads(json.dumps(info)) == info
    assert info["cpu"] == cpu_model() and info["cpu"]
    assert 1 <= info["cpus"] <= (os.cpu_count() or 1)
    assert info["jax"] == jax.__version__
    if os.path.exists("/proc/cpuinfo"):
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            names = [line.split(":", 1)[1].strip() for line in fh if line.startswith("model name")]
        if names:
            assert info["cpu"] == names[0]
