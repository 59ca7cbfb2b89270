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


def test_compile_seconds_counts_a_new_compilation_and_not_a_cached_call():
    from jaxslam._machine import compile_seconds

    before = compile_seconds()
    f = jax.jit(lambda x: jax.numpy.sin(x) * 3.0 + x**2)  # a new function: compiled on first call
    x = jax.numpy.arange(7.0)
    f(x).block_until_ready()
    compiled = compile_seconds()
    assert compiled > before
    f(x).block_until_ready()  # the same shapes: dispatched from the in-memory cache
    assert compile_seconds() == compiled
