import trimesh

from esther_jax import cli


def test_demo_writes_meshes_and_figure(tmp_path, capsys):
    assert cli.main(["demo", "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "middle_tip" in printed and "hands/s" in printed
    assert (tmp_path / "hands.png").stat().st_size > 10_000
    mesh = trimesh.load(tmp_path / "right_flat.ply", process=False)
    assert mesh.is_watertight
