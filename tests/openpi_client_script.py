"""Replay requests through the real openpi-client (PyPI 0.1.2), in its own environment (numpy < 2).

Usage: uv run --isolated --no-project --with openpi-client==0.1.2 --with typing_extensions \
           python openpi_client_script.py PLAN OUT
PLAN (written with the project's codec, read here with openpi_client.msgpack_numpy):
    {"host": str, "port": int, "clients": [[request, ...], ...]}   one list of requests per concurrent client
    optional "wrapper_steering": build the clients with examples/libero_steered_client.py's class for that entry
    optional "api_keys": [str | None, ...], one per client (WebsocketClientPolicy's api_key)
    request: {"obs": observation dict} sent with WebsocketClientPolicy.infer, {"ctrl": control message} sent and
    answered as openpi's current client's episode_start / episode_end do (0.1.2 lacks them), or {"raw": bytes}
    sent as is on the client's own connection (for bytes that infer could not produce).
OUT: {"clients": [{"metadata": ..., "results": [{"reply": dict} | {"error": "Type: message"}, ...]}
                  | {"error": "Type: message", "status": HTTP status} (connecting failed), ...]}
"""

import sys
import threading
from pathlib import Path

from openpi_client import msgpack_numpy
from openpi_client.websocket_client_policy import WebsocketClientPolicy


def send(client, request):
    if "raw" in request or "ctrl" in request:  # the handling of WebsocketClientPolicy.infer and episode_start
        client._ws.send(request["raw"] if "raw" in request else client._packer.pack(request["ctrl"]))
        response = client._ws.recv()
        if isinstance(response, str):
            raise RuntimeError(f"Error in inference server:\n{response}")
        return msgpack_numpy.unpackb(response)
    return client.infer(request["obs"])


def client_class(plan):
    if "wrapper_steering" not in plan:
        return WebsocketClientPolicy
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
    from libero_steered_client import steered_client_class

    return steered_client_class(plan["wrapper_steering"])


def run(cls, host, port, requests, api_key, out, index):
    try:
        client = cls(host, port, api_key=api_key)
    except Exception as err:  # e.g. websockets' InvalidStatus for an upgrade refused with 401
        response = getattr(err, "response", None)
        out[index] = {"error": f"{type(err).__name__}: {err}", "status": getattr(response, "status_code", None)}
        return
    results = []
    for request in requests:
        try:
            results.append({"reply": send(client, request)})
        except Exception as err:  # recorded for the test to check, then the next request goes on the same client
            results.append({"error": f"{type(err).__name__}: {err}"})
    out[index] = {"metadata": client.get_server_metadata(), "results": results}


def main(plan_path, out_path):
    with open(plan_path, "rb") as f:
        plan = msgpack_numpy.unpackb(f.read())
    out = [None] * len(plan["clients"])
    cls = client_class(plan)
    api_keys = plan.get("api_keys") or [None] * len(plan["clients"])
    threads = [threading.Thread(target=run, args=(cls, plan["host"], plan["port"], requests, api_keys[i], out, i))
               for i, requests in enumerate(plan["clients"])]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    with open(out_path, "wb") as f:
        f.write(msgpack_numpy.packb({"clients": out}))


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
