"""LIBERO asset verification: a folder that differs from the hash list is refused with one line naming the file."""

import hashlib

import pytest

from steering_core.rollout import assets
from steering_core.rollout.assets import AssetError, read_asset_list, resolve_assets, verify_assets

FILES = {"a.xml": b"<mujoco/>\n", "meshes/b.obj": b"v 0 0 0\n" * 10, "textures/c.png": b"\x89PNG fake"}


def _write_folder_and_list(tmp_path):
    """Return (folder, list): c.png is listed by git blob id, the others by sha256 and size."""
    folder = tmp_path / "assets"
    lines = ["# a tiny list in the upstream format"]
    for name, data in FILES.items():
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_bytes(data)
        if name.endswith(".png"):
            blob = hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()
            lines.append(f"{assets.BLOB_PREFIX}{blob}  {name}")
        else:
            lines.append(f"{hashlib.sha256(data).hexdigest()}  {len(data)}  {name}")
    listing = tmp_path / "list.sha256"
    listing.write_text("\n".join(lines) + "\n")
    return folder, listing


def test_matching_folder_verifies(tmp_path):
    folder, listing = _write_folder_and_list(tmp_path)
    (folder / "extra.txt").write_text("not listed: ignored")
    assert verify_assets(folder, listing) == folder.resolve()
    assert [entry.kind for entry in read_asset_list(listing)] == ["sha256", "sha256", "git blob id"]


@pytest.mark.parametrize(
    ("name", "data", "problem"),
    [
        ("meshes/b.obj", b"v 1 0 0\n" + b"v 0 0 0\n" * 9, "meshes/b.obj: sha256 "),
        ("a.xml", b"<mujoco />\n", "a.xml: 11 bytes, expected 10"),
        ("textures/c.png", b"\x89PNG fakf", "textures/c.png: git blob id "),
    ],
)
def test_differing_file_is_refused_with_one_line_naming_it(tmp_path, name, data, problem):
    folder, listing = _write_folder_and_list(tmp_path)
    (folder / name).write_bytes(data)
    with pytest.raises(AssetError) as raised:
        verify_assets(folder, listing)
    message = str(raised.value)
    assert "\n" not in message
    assert message.startswith(f"LIBERO assets in {folder.resolve()} differ from list.sha256: {problem}")
    assert message.endswith("(1 of 3 files differ)")


def test_missing_files_are_counted(tmp_path):
    folder, listing = _write_folder_and_list(tmp_path)
    (folder / "a.xml").unlink()
    (folder / "textures/c.png").unlink()
    with pytest.raises(AssetError, match=r": a\.xml: missing \(2 of 3 files differ\)\ntextures/c\.png: missing$"):
        verify_assets(folder, listing)


def test_a_verified_folder_is_not_rehashed(tmp_path, monkeypatch):
    folder, listing = _write_folder_and_list(tmp_path)
    verify_assets(folder, listing)
    monkeypatch.setattr(assets, "_problem", lambda folder, entry: pytest.fail("rehashed"))
    assert verify_assets(folder, listing) == folder.resolve()


def test_malformed_list_line_is_named(tmp_path):
    listing = tmp_path / "list.sha256"
    listing.write_text("# header\nabc  12  a.xml\n")
    with pytest.raises(ValueError, match=r"list\.sha256:2: expected `<sha256>  <size>  <path>`"):
        read_asset_list(listing)


def test_download_leaves_assets_to_hf_libero():
    assert resolve_assets("download") is None


def test_installed_assets_match_upstream_list():
    entries = read_asset_list()
    assert len(entries) == 585 and sum(entry.size is None for entry in entries) == 30
    folder = resolve_assets("installed")
    assert folder.name == "assets" and folder.parent.name == assets.ASSET_MODULE
