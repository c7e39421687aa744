"""profiles/memory.py's instruments, and what a long run keeps per frame (docs/tracking.md "Memory over long runs").

The profile's figures are only as good as its two instruments: the current resident set size (which must fall when
memory is given back, unlike the peak ``ru_maxrss``) and the byte count of an object graph (which must see an image
hidden behind a reference or a closure). The odometry keeps one record per frame for the whole run; these tests
check that a record holds no image (a few hundred bytes, not the 77 KB of a 160x120 frame).
"""

from __future__ import annotations

import importlib.util
import mmap
import resource
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def memory():
    spec = importlib.util.spec_from_file_location("mgso_profile_memory", ROOT / "profiles" / "memory.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    yield mod
    sys.modules.pop(spec.name, None)


def test_rss_is_the_current_size_not_the_peak(memory):
    # 64 MiB of fresh anonymous pages, every one touched. Not a NumPy array: after other tests the allocator may
    # hand back memory it kept resident, and the size would not move (seen in the full suite)
    size = 64 * 2**20
    before = memory.rss_bytes()
    block = mmap.mmap(-1, size)
    for off in range(0, size, mmap.PAGESIZE):
        block[off] = 1
    held = memory.rss_bytes()
    block.close()
    after = memory.rss_bytes()
    assert held - before > 48 * 2**20
    assert held - after > 48 * 2**20  # the peak (ru_maxrss) would stay where it was
    # negative control: the peak does not come down, which is why the profile does not use it
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    assert peak >= held - 2**20


def test_deep_size_sees_an_image_behind_a_reference_or_a_closure(memory):
    class Record:
        def __init__(self, **kw):
            self.__dict__.update(kw)

    image = np.zeros((120, 160), np.float32)
    plain = Record(index=1, pose=np.eye(4))
    held = Record(index=1, pose=np.eye(4), image=image)
    closure = Record(index=1, pose=np.eye(4), rgb=lambda f=image: f)
    small = memory.deep_size(plain)
    assert small < 2000
    assert memory.deep_size(held) >= small + image.nbytes
    assert memory.deep_size(closure) >= small + image.nbytes
    # a view counts the buffer it keeps alive
    assert memory.deep_size(Record(v=image[:2])) >= image.nbytes


def test_growth_is_measured_from_the_warmup_sample(memory):
    samples = [{"frame": 0, "tag": "start", "rss_mb": 100.0}, {"frame": 1000, "tag": "", "rss_mb": 200.0},
               {"frame": 2000, "tag": "", "rss_mb": 205.0}, {"frame": 3000, "tag": "", "rss_mb": 210.0},
               {"frame": 3000, "tag": "after finish", "rss_mb": 400.0}]
    g = memory.growth(samples, warmup=1000)
    assert g["warmup_frame"] == 1000
    assert g["growth_pct"] == pytest.approx(5.0)
    assert g["bytes_per_frame"] == pytest.approx(5000.0)
    assert g["bytes_per_frame_fit"] == pytest.approx(5000.0)
    assert memory.growth(samples, warmup=3000)["growth_pct"] is None  # one sample after warm-up: no growth


def test_a_frame_record_holds_no_image(memory, wp_device):
    from mgso.config import Config
    from mgso.odometry import Odometry, geometry_for

    spec, frames = memory.synthetic_frames(24, 160, 120)
    k = spec.intrinsics
    cfg = Config()
    odo = Odometry(geometry_for(k.width, k.height, k.fx, k.fy, k.cx, k.cy, cfg), cfg, device=wp_device)
    results = [odo.process(f) for f in frames]
    assert sum(f.pose_valid for f in odo.frames) >= 10  # the odometry initialised and tracked
    image_bytes = 160 * 120 * 4
    per_record = memory.bytes_each(odo.frames)
    per_result = memory.bytes_each(results)
    assert per_record < image_bytes / 20, per_record
    assert per_result < image_bytes / 10, per_result
    per_keyframe = memory.bytes_each(odo.keyframes.values())
    assert per_keyframe < image_bytes / 20, per_keyframe
    # negative control: a record that kept its frame's image would be seen
    odo.frames[-1].image = np.zeros((120, 160), np.float32)
    assert memory.bytes_each(odo.frames[-5:]) > image_bytes / 5
