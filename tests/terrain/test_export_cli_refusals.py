"""neuralmap-export refuses bad options before anything is written: exit 2, one error line
naming this CLI's option (not train.py's) and the fix."""

from __future__ import annotations

from pathlib import Path

import pytest

from neuralmap.dem import load_tile
from neuralmap.terrain.blockwise import BlockwiseTerrainNet
from neuralmap.terrain.export import save_map
from neuralmap.terrain.export_cli import main


@pytest.fixture(scope="module")
def sample_map(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tile = load_tile("jacksboro")  # a sample: the map records it as its source
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=64, hidden=4, n_frequencies=2)
    return save_map(net, tmp_path_factory.mktemp("run") / "neural_map.pt")


@pytest.mark.parametrize(("extra", "expected"), [
    (["--spacing", "-1"], "error: --spacing must be a grid spacing > 0 in metres, got -1.0"),
    (["--spacing", "5"], "remove --spacing"),  # the sample carries its own spacing
    (["--units", "parsecs"], "error: --units must be one of metres, degrees, got 'parsecs'"),
    (["--layers", "[foo]"], "error: --layers: unknown or empty ['foo']; choose from"),
])
def test_bad_export_options_name_the_option(sample_map: Path, tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str],
                                            extra: list[str], expected: str) -> None:
    out = tmp_path / "tif"
    with pytest.raises(SystemExit) as info:
        main([str(sample_map), "--out", str(out), *extra])
    err = capsys.readouterr().err
    assert info.value.code == 2 and err.count("\n") == 1, err
    assert expected in err and "--data." not in err, err
    assert not out.exists() or not any(out.iterdir())
