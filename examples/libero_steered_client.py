"""Run openpi's LIBERO example (`examples/libero/main.py`) with a steering entry added to every observation.

UNTESTED against the real simulator: the wrapped client class is tested with the real openpi-client on loopback
(tests/test_serve.py), but this script has not been run inside LIBERO. Run it from openpi's repository root, in the LIBERO client environment
(the one `examples/libero/main.py` runs in), against `latent-steering serve`:

    python /path/to/latent-steering/examples/libero_steered_client.py \
        --steering '{"pair": "open_vs_close", "layer": 12, "alpha": 2.0}' \
        --args.host 127.0.0.1 --args.port 8000 --args.task-suite-name libero_spatial

`--steering` is one entry or a JSON list of entries (keys pair, layer, alpha, optional direction and alpha_units:
"residual_norm", the default, the evaluation's unit, or "vector"); every other
flag goes to openpi's `eval_libero` unchanged. The LIBERO example builds its client from
`openpi_client.websocket_client_policy.WebsocketClientPolicy` when it starts, so replacing that class before
calling it is enough: main.py itself is not edited.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import openpi_client.websocket_client_policy as websocket_client_policy


def steered_client_class(steering: dict | list) -> type:
    """Return a WebsocketClientPolicy subclass that adds `steering` to every observation it sends."""

    class SteeredWebsocketClientPolicy(websocket_client_policy.WebsocketClientPolicy):
        def infer(self, obs: dict) -> dict:
            return super().infer({**obs, "steering": steering})

    return SteeredWebsocketClientPolicy


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], add_help=False)
    parser.add_argument("--steering", required=True, help="JSON steering entry or list of entries")
    parser.add_argument("--libero-dir", type=Path, default=Path("examples/libero"),
                        help="folder of openpi's LIBERO main.py (default: examples/libero under the current folder)")
    args, rest = parser.parse_known_args()
    steering = json.loads(args.steering)
    websocket_client_policy.WebsocketClientPolicy = steered_client_class(steering)

    sys.path.insert(0, str(args.libero_dir))
    import main as libero_main  # openpi's examples/libero/main.py
    import tyro

    logging.basicConfig(level=logging.INFO)  # as main.py does when run directly
    sys.argv = [sys.argv[0], *rest]
    tyro.cli(libero_main.eval_libero)


if __name__ == "__main__":
    main()
