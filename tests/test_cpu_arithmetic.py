"""A seeded deep learner gives the same numbers on Intel CPUs with AVX-512 and AVX2: MKL runs one code path on both."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest
import torch as th

from sb3_sfgpi.common.cpu_arithmetic import MKL_CODE_PATH, mkl_code_path
from sb3_sfgpi.common.software import cpu_model, software_versions

pytestmark = pytest.mark.skipif(mkl_code_path() is None, reason="torch has no MKL here (ARM, macOS)")

#: A seeded SFDQN with MLP SFs, 400 steps of deep-sea-treasure, and the hash of its parameters.
TRAIN = textwrap.dedent(
    """
    import hashlib
    import mo_gymnasium
    import torch
    from sb3_sfgpi import SFDQN

    torch.set_num_threads({threads})
    env = mo_gymnasium.make("deep-sea-treasure-v0")
    model = SFDQN("MlpPolicy", env, learning_starts=50, batch_size=64, seed=0,
                  policy_kwargs={{"net_arch": [96, 160]}}, weights=[0.3, 0.7])
    model.learn(400)
    digest = hashlib.sha256()
    for value in model.policy.state_dict().values():
        digest.update(value.numpy().tobytes())
    print(digest.hexdigest())
    """
)


def _run(code: str, **environment: str) -> subprocess.CompletedProcess:
    # as a user's shell has it: no MKL_CBWR (the package's import sets it) unless ``environment`` names one
    env = {key: value for key, value in os.environ.items() if key != "MKL_CBWR"} | environment
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)


def test_the_package_pins_mkl_to_one_code_path_and_records_it():
    # MKL takes Intel's named code paths on Intel CPUs only; elsewhere it keeps its own choice, in strict mode
    assert os.environ["MKL_CBWR"] == MKL_CODE_PATH
    th.ones(2, 2) @ th.ones(2, 2)
    expected = MKL_CODE_PATH if "Intel" in cpu_model() else "AUTO,STRICT"
    assert mkl_code_path() == expected
    assert software_versions()["mkl"] == expected


def test_the_package_keeps_a_code_path_the_user_chose():
    # MKL_CBWR=COMPATIBLE: the same bits on Intel and AMD CPUs, at more time per update (docs, deep_fronts)
    code = (
        "import warnings; warnings.simplefilter('error')\n"
        "import sb3_sfgpi, torch\n"
        "from sb3_sfgpi.common.cpu_arithmetic import mkl_code_path, warn_unless_pinned\n"
        "torch.ones(2, 2) @ torch.ones(2, 2); warn_unless_pinned(); print(mkl_code_path())"
    )
    assert _run(code, MKL_CBWR="COMPATIBLE").stdout.strip() == "COMPATIBLE"


def test_a_seeded_deep_learner_trains_the_same_bits_on_avx2_and_on_the_cpus_own_instructions():
    # MKL, torch's own kernels and numpy's OpenBLAS made to see an AVX2 CPU; on an AVX-512 machine MKL's unpinned
    # kernels gave these two runs different parameters from the first update on
    here = _run(TRAIN.format(threads=1)).stdout
    avx2_cpu = {"MKL_ENABLE_INSTRUCTIONS": "AVX2", "ATEN_CPU_CAPABILITY": "avx2", "OPENBLAS_CORETYPE": "Haswell"}
    avx2 = _run(TRAIN.format(threads=1), **avx2_cpu).stdout
    two_threads = _run(TRAIN.format(threads=2)).stdout
    assert len(here.strip()) == 64
    assert here == avx2 == two_threads


def test_a_deep_learner_warns_when_torch_multiplied_matrices_before_the_package_was_imported():
    build = TRAIN.format(threads=1).replace("model.learn(400)", "")
    assert f"not {MKL_CODE_PATH}" in _run("import torch; torch.ones(2, 2) @ torch.ones(2, 2)\n" + build).stderr
    assert "not AVX2" not in _run(build).stderr
