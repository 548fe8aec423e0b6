"""benchmarks.step_budget: what a training step spends in Embree and at which rows its networks run."""
import pytest

from benchmarks.step_budget import measure, rows
from fit_fixtures import write_rendered_scene
from nefii.fit.config import resolve_config
from nefii.fit.session import prepare_fit


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    return write_rendered_scene(tmp_path_factory.mktemp("scene"), res=16, n_train=6, n_test=2)


def test_a_step_budget_counts_the_estimator_rays_and_restores_the_geometry(tiny_scene):
    cfg = resolve_config("tiny", [])
    session = prepare_fit(cfg, tiny_scene)
    b = measure(session.trainer, session.geometry, steps=3, repeats=1)
    directions = 3 * cfg.num_samples * cfg.batch_pixels
    assert cfg.batch_pixels <= b.embree_rays <= 2 * directions   # a closest hit, at most a shadow ray, per live direction
    assert b.cache_rows >= cfg.batch_pixels and b.material_rows >= cfg.batch_pixels   # Eq. 7's first hits at least
    assert 0 < b.embree_ms < b.step_ms and b.cache_pass_ms > 0 and b.material_pass_ms > 0
    assert not {"intersect", "occluded"} & set(vars(session.geometry))      # the timing wrappers are gone
    table = dict(rows(b, samples_per_step=directions, closest_rate=1e6))
    assert table["step time at 15% of Embree's closest-hit rate"] == f"{1000 * directions / 0.15e6:.1f} ms"
