"""Known SAE releases and their offline resolution to folders in the Hugging Face cache.

Entries copy the facts of SAELens's `pretrained_saes.yaml` (repo, folder per SAE id, Neuronpedia
id, norm scaling factor). Nothing is downloaded: a release resolves to a folder already in the
local cache (`models--<org>--<name>/snapshots/<rev>/<folder>/`) or in a user-given folder that
holds `<folder>/` (the layout of `hf download --local-dir`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from steering_core.sae.formats import FOLDER_FILES, SPARSITY_FILE

NEURONPEDIA_FEATURE_URL = "https://neuronpedia.org/{neuronpedia_id}/{index}"
HUB_REPO_DIR = "models--{org}--{name}"  # huggingface_hub cache layout
DOWNLOAD_COMMAND = "hf download {repo_id} --include '{folder}/*' --local-dir {local_dir}"


@dataclass(frozen=True)
class SaeEntry:
    """One SAE of a release: its folder in the repo and optional Neuronpedia id and norm factor."""

    folder: str
    neuronpedia_id: str | None = None
    norm_scaling_factor: float | None = None  # folded in when cfg asks for "expected_average_only_in"


@dataclass(frozen=True)
class Release:
    """A named set of SAEs stored in one Hugging Face repo."""

    name: str
    repo_id: str
    model: str
    saes: dict[str, SaeEntry] = field(default_factory=dict)


RELEASES: dict[str, Release] = {
    release.name: release
    for release in (
        Release(
            name="gemma-2b-it-res-jb",
            repo_id="jbloom/Gemma-2b-IT-Residual-Stream-SAEs",
            model="gemma-2b-it",
            saes={
                "blocks.12.hook_resid_post": SaeEntry(
                    "gemma_2b_it_blocks.12.hook_resid_post_16384", "gemma-2b-it/12-res-jb"
                ),
            },
        ),
        Release(
            name="gemma-2b-res-jb",
            repo_id="jbloom/Gemma-2b-Residual-Stream-SAEs",
            model="gemma-2b",
            saes={
                "blocks.0.hook_resid_post": SaeEntry(
                    "gemma_2b_blocks.0.hook_resid_post_16384_anthropic", "gemma-2b/0-res-jb"
                ),
                "blocks.6.hook_resid_post": SaeEntry(
                    "gemma_2b_blocks.6.hook_resid_post_16384_anthropic_fast_lr", "gemma-2b/6-res-jb"
                ),
                "blocks.10.hook_resid_post": SaeEntry(
                    "gemma_2b_blocks.10.hook_resid_post_16384", "gemma-2b/10-res-jb"
                ),
                "blocks.12.hook_resid_post": SaeEntry(
                    "gemma_2b_blocks.12.hook_resid_post_16384", "gemma-2b/12-res-jb", 0.21381938399317255
                ),
                # SAELens lists no Neuronpedia id for layer 17
                "blocks.17.hook_resid_post": SaeEntry("gemma_2b_blocks.17.hook_resid_post_16384"),
            },
        ),
    )
}


def get_entry(release: str, sae_id: str | None) -> tuple[str, SaeEntry]:
    """Return (sae_id, entry) of a release; `sae_id` may be omitted when the release has one SAE."""
    if release not in RELEASES:
        raise ValueError(f"unknown SAE release {release!r}; known releases: {sorted(RELEASES)}")
    saes = RELEASES[release].saes
    if sae_id is None and len(saes) == 1:
        sae_id = next(iter(saes))
    if sae_id is None:
        raise ValueError(f"SAE release {release!r} holds several SAEs; pass an SAE id, one of {list(saes)}")
    if sae_id not in saes:
        raise ValueError(
            f"SAE release {release!r} has no SAE id {sae_id!r}; valid ids: {list(saes)}; "
            "pass another release, an SAE folder or file, or no SAE"
        )
    return sae_id, saes[sae_id]


def find_by_folder(folder_name: str) -> tuple[str, str, SaeEntry] | None:
    """Return (release, sae_id, entry) whose repo folder is named `folder_name`, if any."""
    for release in RELEASES.values():
        for sae_id, entry in release.saes.items():
            if entry.folder == folder_name:
                return release.name, sae_id, entry
    return None


def hub_cache_dir() -> Path:
    """Return the Hugging Face hub cache folder, honouring the same variables as huggingface_hub."""
    for variable in ("HF_HUB_CACHE", "HUGGINGFACE_HUB_CACHE"):
        if os.environ.get(variable):
            return Path(os.environ[variable]).expanduser()
    if os.environ.get("HF_HOME"):
        return Path(os.environ["HF_HOME"]).expanduser() / "hub"
    cache_home = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache").expanduser()
    return cache_home / "huggingface" / "hub"


def resolve_release(release: str, sae_id: str | None, *, local_dir: str | os.PathLike | None = None) -> Path:
    """Return the local folder of one release SAE (user folder first, then the hub cache).

    Raises FileNotFoundError naming the repo, folder and files to obtain and where to put them.
    """
    sae_id, entry = get_entry(release, sae_id)
    repo_id = RELEASES[release].repo_id
    candidates = _cache_candidates(repo_id, entry.folder)
    if local_dir is not None:
        candidates.insert(0, Path(local_dir).expanduser() / entry.folder)
    for folder in candidates:
        if all((folder / name).is_file() for name in FOLDER_FILES):
            return folder
    org, name = repo_id.split("/")
    target = Path(local_dir) if local_dir is not None else Path("<dir>")
    raise FileNotFoundError(
        f"SAE {release!r} / {sae_id!r} is not on this machine (no network access is attempted).\n"
        f"  Looked in: {', '.join(str(path) for path in candidates) or '(no snapshot of the repo)'}\n"
        f"  Hub cache: {hub_cache_dir() / HUB_REPO_DIR.format(org=org, name=name)}/snapshots/<rev>/{entry.folder}/\n"
        f"  Obtain from the Hugging Face repo `{repo_id}` the folder `{entry.folder}/` with files "
        f"{', '.join(FOLDER_FILES)} (optional {SPARSITY_FILE}), e.g. on a machine with network:\n"
        f"    {DOWNLOAD_COMMAND.format(repo_id=repo_id, folder=entry.folder, local_dir=target)}\n"
        f"  then pass that directory as the SAE folder (`--sae-dir {target}`, or `--sae {target}/{entry.folder}`), "
        "or copy the repo into the hub cache above."
    )


def _cache_candidates(repo_id: str, folder: str) -> list[Path]:
    """Return `<snapshot>/<folder>` for the repo's snapshots in the hub cache, `refs/main` first."""
    org, name = repo_id.split("/")
    repo_dir = hub_cache_dir() / HUB_REPO_DIR.format(org=org, name=name)
    snapshots = sorted((repo_dir / "snapshots").glob("*")) if (repo_dir / "snapshots").is_dir() else []
    main_ref = repo_dir / "refs" / "main"
    if main_ref.is_file():
        main = repo_dir / "snapshots" / main_ref.read_text().strip()
        snapshots.sort(key=lambda path: path != main)
    return [snapshot / folder for snapshot in snapshots]
