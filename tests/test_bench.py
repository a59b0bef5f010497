"""The benchmarks' own arithmetic: what `bench_fitness --trace` reports of a device trace."""

from __future__ import annotations

import jax
import pytest

from experiments.bench_fitness import trace_summary

# Two streams: a fusion 0-2 us and a Warp kernel 1-4 us overlap (busy 0-4), an idle gap, then a
# copy 6-7 us and a gemm 7-9 us (busy 6-9); a line that is not a stream's is not counted.
XSPACE = """
planes { id: 1 name: "/device:GPU:0"
  lines { id: 1 name: "Stream #13(Compute)" timestamp_ns: 1000
    events { metadata_id: 1 offset_ps: 0 duration_ps: 2000000 }
    events { metadata_id: 3 offset_ps: 6000000 duration_ps: 1000000 }
    events { metadata_id: 4 offset_ps: 7000000 duration_ps: 2000000 }
  }
  lines { id: 2 name: "Stream #14(Compute)" timestamp_ns: 1000
    events { metadata_id: 2 offset_ps: 1000000 duration_ps: 3000000 }
  }
  lines { id: 3 name: "TensorFlow Name Scope" timestamp_ns: 1000
    events { metadata_id: 5 offset_ps: 0 duration_ps: 40000000 }
  }
  event_metadata { key: 1 value { id: 1 name: "loop_add_fusion" } }
  event_metadata { key: 2 value { id: 2 name: "kinematics_cuda_kernel_forward" } }
  event_metadata { key: 3 value { id: 3 name: "MemcpyD2D" } }
  event_metadata { key: 4 value { id: 4 name: "sm90_xmma_gemm_f32f32" } }
  event_metadata { key: 5 value { id: 5 name: "collect" } }
}
planes { id: 2 name: "/host:CPU" }
"""


def profile(text: str):
    data = jax.profiler.ProfileData
    return data.from_serialized_xspace(data.text_proto_to_serialized_xspace(text))


def test_trace_summary_counts_busy_time_once_across_streams():
    s = trace_summary(profile(XSPACE))
    assert s["kernels"] == 4
    assert s["span_ms"] == pytest.approx(9e-3)
    assert s["busy_ms"] == pytest.approx(7e-3)  # 0-4 and 6-9 us: the overlap counted once
    assert s["idle_ms"] == pytest.approx(2e-3)
    assert s["by_kind_ms"] == pytest.approx({"xla": 2e-3, "warp": 3e-3, "copy": 1e-3, "gemm": 2e-3})
    assert [name for name, *_ in s["top"]] == [
        "kinematics_cuda_kernel_forward", "loop_add_fusion", "sm90_xmma_gemm_f32f32", "MemcpyD2D"
    ]


def test_trace_summary_is_none_without_a_gpu():
    assert trace_summary(profile('planes { id: 2 name: "/host:CPU" }')) is None
