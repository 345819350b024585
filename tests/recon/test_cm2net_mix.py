"""CM²Net's mixed training source (``mix_forward_model``, ``mix_fraction``, ``mix_synth``): the
config's rules and hash, the epoch's items (how many volumes, their seeds and patches) and the
patches the dataset makes from each source. Toy sizes: well under a second each."""

from __future__ import annotations

import numpy as np
import pytest
from tiny_net import tiny

from cm2optics.recon.net.config import ConfigError
from cm2optics.recon.net.data import MIX_SEED_OFFSET, PatchDataset, PatchSource, epoch_items, steps_per_epoch

pytestmark = pytest.mark.usefixtures("one_torch_thread")

MIX = dict(mix_forward_model="toy:gaussian", mix_fraction=0.5, mix_synth={"view_px": 48, "patches_per_volume": 2})


def test_a_mixed_source_enters_the_hash_only_when_set_and_is_checked():
    plain = tiny()
    assert plain.with_changes(mix_synth={}, mix_fraction=0.0, mix_forward_model="").hash() == plain.hash()
    mixed = tiny(**MIX)
    assert mixed.hash() != plain.hash()
    assert mixed.with_changes(mix_fraction=0.25).hash() != mixed.hash()
    assert mixed.mix_config().synth.view_px == 48 and mixed.mix_config().synth.patch_px == plain.synth.patch_px
    for bad, match in [
        (dict(mix_forward_model="toy:gaussian"), "needs both"),
        (dict(mix_fraction=0.5), "needs both"),
        (dict(MIX, mix_fraction=1.5), "mix_fraction"),
        (dict(MIX, mix_synth={"patch_px": 16}), "must stay the network's"),
        (dict(MIX, mix_synth={"view": 48}), "mix_synth: unknown synth parameter"),
        (dict(mix_synth={"view_px": 48}), "mix_forward_model is empty"),
    ]:
        with pytest.raises(ConfigError, match=match):
            tiny(**bad)


def test_an_epoch_mixes_round_fraction_times_volumes_from_their_own_seed():
    config = tiny(train_volumes=5, batch_size=2, **MIX)  # round(0.5 · 5) = 2 mixed volumes
    for epoch in (0, 3):
        items = epoch_items(config, epoch)
        mixed = [i for i in items if i.source == 1]
        plain = [i for i in items if i.source == 0]
        assert len({i.volume for i in mixed}) == 2 and len({i.volume for i in plain}) == 3
        assert {i.seed for i in mixed} == {config.seed + MIX_SEED_OFFSET} and {i.seed for i in plain} == {config.seed}
        assert sorted(i.patch for i in mixed) == [0, 0, 1, 1] and len(plain) == 3 * 4
        assert {i.volume for i in items} == set(range(5 * epoch, 5 * epoch + 5))
        assert len(items) // 2 == steps_per_epoch(config) == (2 * 2 + 3 * 4) // 2
    assert epoch_items(config, 3) == epoch_items(config, 3)
    assert all(i.source == 0 for i in epoch_items(tiny(train_volumes=5), 0))


def test_the_dataset_makes_each_item_from_its_own_source():
    config = tiny(train_volumes=2, **MIX)
    items = epoch_items(config, 0)
    dataset = PatchDataset(config, items)
    p = config.synth.patch_px
    for source, made in ((0, PatchSource(config)), (1, PatchSource(config.mix_config()))):
        k = next(n for n, i in enumerate(items) if i.source == source)
        patch = dataset[k]
        assert patch["views"].shape == (9, p, p)
        expected = made.patch(items[k])
        for key in ("views", "demixed", "volume"):
            np.testing.assert_array_equal(patch[key].numpy(), expected[key])
    assert dataset._sources[1].config.synth.view_px == 48 and dataset._sources[0].config.synth.view_px == 64
