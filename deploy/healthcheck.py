"""The image's HEALTHCHECK: exit 0 when the container's blendsplat process is alive.

``serve`` and ``up``: GET /healthz on the HTTP port (``--http-port``, else BLENDSPLAT_HTTP_PORT, else 8080; https
when BLENDSPLAT_TLS_CERT_FILE is set). ``worker``: GET /metrics on its ``--metrics-port`` when it serves one, else
healthy while it runs (the worker has no other endpoint; a hung job is caught by its lease). ``migrate`` and the
other one-shot commands: healthy while they run. Standard library only; reads PID 1's command line.
"""

from __future__ import annotations

import os
import ssl
import sys
import urllib.request


def command_line(pid: int = 1) -> list[str]:
    with open(f"/proc/{pid}/cmdline", "rb") as f:
        return [a.decode(errors="replace") for a in f.read().split(b"\0") if a]


def option(args: list[str], name: str) -> str | None:
    for i, a in enumerate(args):
        if a == name and i + 1 < len(args):
            return args[i + 1]
        if a.startswith(name + "="):
            return a.split("=", 1)[1]
    return None


def probe_url(args: list[str], env: dict[str, str]) -> str | None:
    """The URL to probe for this command line, or None when the process running is all there is to check."""
    if "serve" in args or "up" in args:
        port = option(args, "--http-port") or env.get("BLENDSPLAT_HTTP_PORT") or "8080"
        scheme = "https" if env.get("BLENDSPLAT_TLS_CERT_FILE") else "http"
        return f"{scheme}://127.0.0.1:{port}/healthz"
    if "worker" in args:
        port = option(args, "--metrics-port")
        return f"http://127.0.0.1:{port}/metrics" if port and port != "0" else None
    return None


def main() -> int:
    url = probe_url(command_line(), dict(os.environ))
    if url is None:
        return 0
    context = ssl.create_default_context()
    context.check_hostname = False
    context.verify_mode = ssl.CERT_NONE  # loopback: the certificate names the service, not 127.0.0.1
    try:
        with urllib.request.urlopen(url, timeout=4, context=context) as response:
            return 0 if response.status == 200 else 1
    except OSError as e:
        print(f"unhealthy: {url}: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
