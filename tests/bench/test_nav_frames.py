"""The navigation cycle's frames (bench nav.cycle): the approach there and back, so the daemon's
cycling never jumps from contact to 10 m inside the row the p99 target applies to."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
from oibar_bench.nav import there_and_back  # noqa: E402


def test_the_cycled_frames_only_ever_step_to_a_neighbour(tmp_path):
    src = tmp_path / "frames"
    src.mkdir()
    for i in range(5):
        (src / f"{i:06d}.jpg").write_bytes(bytes([i]))
    out = there_and_back(src, tmp_path / "out")
    order = [f.read_bytes()[0] for f in sorted(out.iterdir())]
    assert order == [0, 1, 2, 3, 4, 3, 2, 1]
    cycled = order * 3 + order[:1]  # what the daemon reads, wrapping
    assert max(abs(a - b) for a, b in zip(cycled[:-1], cycled[1:], strict=True)) == 1
