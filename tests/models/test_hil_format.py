"""The reader against the real writer: a few frames rendered by oibar_hil.dataset (OpenGL; skipped
where no headless EGL context can be made), read back, labels consistent with the camera."""

from __future__ import annotations

import numpy as np
import pytest

from oibar.geometry.camera import project_camera_points as project_np
from oibar_models.data import frame_cache, input_intrinsics, load_sequence


@pytest.mark.slow
def test_reads_frames_written_by_oibar_hil(tmp_path, headless_gl):
    from oibar_hil import dataset as hds

    spec = hds.PAPER_SEQUENCES[2]  # perlin: the cheapest scene to render
    hds.generate_dataset(tmp_path, [spec], frames_limit=3, workers=1, progress=False)
    seq = load_sequence(tmp_path / spec.name, verify_hashes=True)
    assert len(seq) == 3 and seq.width_px == 744 and seq.height_px == 480
    frames = frame_cache(seq, (248, 160), None)
    assert frames.shape == (3, 160, 248, 3)
    uv = project_np(input_intrinsics(seq, (248, 160)), seq.T_cam_target)
    assert np.all((uv > 0) & (uv < [248, 160]))  # the fixture is in view at the start
