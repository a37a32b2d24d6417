"""The README's "Real data" commands, run as written (reconstructions at half size), give
recognisable results: the hand agrees with an independent FISTA reconstruction, the
tilted USAF target's in-focus depth moves steadily across it, and the volume from the
stack model agrees with the volume from the measured stack. The former defaults
(Richardson–Lucy, 150 iterations) are run beside them and must do worse on the hand."""

import pytest

from benchmarks.bench_real_data import readme_commands, run, scores


def test_readme_lists_the_real_data_commands():
    commands = readme_commands()
    assert [c[:2] for c in commands] == [["diffcam", "data"], ["diffcam", "reconstruct"],
                                         ["diffcam", "data"], ["diffcam", "reconstruct"],
                                         ["diffcam", "reconstruct"], ["diffcam", "fit"],
                                         ["diffcam", "reconstruct"]]
    assert all("--downsample" not in c for c in commands)   # full size as written


@pytest.mark.slow
def test_readme_real_data_commands(tmp_path):
    rows, work = run(downsample=2, fit_budget=25, work=tmp_path)
    assert all(r["wall_s"] > 0 for r in rows) and len(rows) == 10  # 7 commands, 3 befores
    s = scores(work, downsample=2)     # measured: 0.987 / 0.958, ramps −0.69 / −0.49,
    # model ramp −0.82, model volume 0.864
    assert s["hand_after"] > 0.97
    assert s["hand_after"] > s["hand_before"] + 0.01  # the former default: 0.96
    assert s["usaf_ramp_after"] < -0.6                # the target's depth ramp
    assert s["usaf_ramp_model"] < -0.5
    assert s["usaf_model_volume_pearson"] > 0.8
