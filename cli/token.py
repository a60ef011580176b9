"""``lightprobe token``: print the API bearer token (creating it if the service never ran)."""

from __future__ import annotations

import argparse
import os

__all__ = ["main"]


def main(argv: list[str]) -> int:
    from lightprobe.cli.serve import state_dir_from
    from lightprobe.core.command import run_command
    from lightprobe.device.service.auth import load_or_create_token, read_token

    p = argparse.ArgumentParser(prog="lightprobe token", description="Print the API bearer token "
                                "that write endpoints (PUT /api/v1/config) require.")
    p.add_argument("--state-dir", default=None, help="state directory (default $STATE_DIRECTORY or ./state)")
    p.add_argument("--no-create", action="store_true", help="fail (exit 1) instead of creating a token")
    a = p.parse_args(argv)
    state = state_dir_from(a.state_dir, dict(os.environ))

    def body() -> int:
        tok = read_token(state) if a.no_create else load_or_create_token(state)
        if tok is None:
            print(f"lightprobe: no token in {state} (start the service once)")
            return 1
        print(tok)
        return 0

    return run_command(body)
