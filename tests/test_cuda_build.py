"""CUDA code generation is checked on CPU-only machines: every kernel module is built ahead of time
for sm_90 (the H100) with warp's bundled NVRTC, and the parity check that a GPU session runs is
exercised here with the CPU on both sides."""
import numpy as np
import pytest

from wrenorm import cuda_check


@pytest.fixture(scope="module")
def built():
    return cuda_check.compile_for_cuda(cuda_check.kernel_modules(), arch=90)


def test_every_kernel_module_builds_for_sm90(built):
    assert set(built) == set(cuda_check.kernel_modules())
    for name, res in built.items():
        assert 0 < res["registers"] <= 255, name
        assert res["frame_bytes"] >= 0 and res["cubin_bytes"] > 1000, name


def test_per_thread_frame_grows_with_chain_size(built):
    # the fixed-size rope kernel keeps the whole chain per thread: a longer chain spills more
    assert built["rope_fast[N=16]"]["frame_bytes"] > built["rope_fast[N=8]"]["frame_bytes"]


@pytest.mark.parametrize("n", [8, 16])
def test_tiled_rope_kernel_keeps_its_chain_out_of_local_memory(built, n):
    # the CUDA default (kernels/rope/tiled.py): registers and shared memory only, at most a few spilled words
    res = built[f"rope_tiled[N={n}]"]
    assert res["registers"] <= 255 and res["frame_bytes"] <= 256, res
    assert res["frame_bytes"] < built[f"rope_fast[N={n}]"]["frame_bytes"] or res["frame_bytes"] == 0


def test_swimmer_builds_its_forward_kernel_only(built):
    # nothing differentiates the swimmer: no adjoint kernel (255 registers and a 448-byte frame) in the module
    assert built["swimmer"]["registers"] < 255 and built["swimmer"]["frame_bytes"] <= 256, built["swimmer"]


def test_cubin_reader_rejects_other_files(tmp_path):
    f = tmp_path / "x.cubin"
    f.write_bytes(b"not an elf file")
    with pytest.raises(ValueError, match="not an ELF"):
        cuda_check.cubin_resources(f)


def test_parity_path_runs_and_is_exact_cpu_against_cpu():
    p = cuda_check.parity("cpu")
    assert p["rope"]["status_agree"] == 1.0 and p["rope"]["hit_fraction_cpu"] > 0
    assert p["rope"]["hit_time_max_abs_s"] == 0.0
    assert p["rope"]["observable_status_agree"] == 1.0 and p["rope"]["observable_total_max_rel"] == 0.0
    assert p["swimmer"]["speed_max_rel"] == 0.0 and np.isfinite(p["pd"]["error_max_rel"])
    assert p["pd"]["error_max_rel"] == 0.0
