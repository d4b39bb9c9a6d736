"""`silcr health`: a scheduler's probe of one component (common/health.py says what alive and ready mean).

Exit 0 and one line on stdout when the component is healthy; exit 1 and one line on stderr saying
why not. Run in the component's container (its `--health-file`, and with `--ready` its Zenoh
settings: the same SILCR_* variables the component reads).
"""

from __future__ import annotations

import sys

from silcr.common import health
from silcr.common.config import Config


def run_health(cfg: Config, ready: bool, stale_after: float, timeout: float) -> int:
    path = cfg.health_file or health.DEFAULT_HEALTH_FILE
    try:
        line = health.alive(path, stale_after)
        if ready:
            beat = health.read(path)
            from silcr.common.zenoh_session import open_session, session_config

            conf = session_config(cfg.connect, [], cfg.zenoh_mode, cfg.zenoh_config)
            # A probe must answer within its timeout: give up connecting then (components retry forever).
            conf.insert_json5("connect/timeout_ms", str(int(timeout * 1000)))
            conf.insert_json5("connect/exit_on_failure", "true")
            with open_session(conf) as session:
                if not health.token_visible(session, beat["token"], timeout):
                    raise ValueError(f"{beat['role']} of run {beat['run']}: its liveliness token {beat['token']} is "
                                     f"not visible through {', '.join(cfg.connect) or 'the local router'} within "
                                     f"{timeout:g}s (not joined, or the router is unreachable)")
            line += f"; token {beat['token']} visible"
    except ValueError as e:
        print(f"silcr health: {e}", file=sys.stderr)
        return 1
    except Exception as e:  # zenoh raises its own errors for an endpoint it cannot reach
        print(f"silcr health: cannot check the liveliness token ({type(e).__name__}: {e})", file=sys.stderr)
        return 1
    print(f"silcr health: ok: {line}")
    return 0
