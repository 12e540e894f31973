"""Ray for a sweep: a local instance, or a cluster joined as Ray documents it today (token authentication)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any


def joined_ray(address: str | None, num_cpus: int | None) -> Any:
    """Ray, initialised: the given or ``RAY_ADDRESS``'s cluster, or a local one with ``num_cpus`` CPUs."""
    local = address is None and not os.environ.get("RAY_ADDRESS")
    if not local:
        _authenticate_with_token()  # before Ray is imported: it reads RAY_AUTH_MODE then
    try:
        import ray
    except ImportError as error:
        raise ValueError("sweeps run on Ray: pip install 'sb3-sfgpi[sweep]'") from error
    if not ray.is_initialized():
        kwargs = {"num_cpus": num_cpus or os.cpu_count(), "include_dashboard": False} if local else {}
        try:
            ray.init(address=address, log_to_driver=False, **kwargs)
        except (ConnectionError, RuntimeError) as error:  # RuntimeError: token authentication without a token
            if local:
                raise
            raise ValueError(_join_advice(address or os.environ["RAY_ADDRESS"], error)) from None
    return ray


def _authenticate_with_token() -> None:
    """
    Join a cluster with token authentication where a token is at hand (``RAY_AUTH_TOKEN``, the file
    ``RAY_AUTH_TOKEN_PATH`` names, or ``~/.ray/auth_token``, where ``ray start`` keeps it): Ray ≥ 2.59 turns it on for
    clusters started with ``ray start``, but a driver that joins by address uses it only with ``RAY_AUTH_MODE=token``,
    read when Ray is imported. A ``RAY_AUTH_MODE`` the user set is left as it is.
    """
    if "RAY_AUTH_MODE" in os.environ:
        return
    path = os.environ.get("RAY_AUTH_TOKEN_PATH")
    token_file = Path(path).expanduser() if path else Path.home() / ".ray" / "auth_token"
    if os.environ.get("RAY_AUTH_TOKEN") or token_file.is_file():
        os.environ["RAY_AUTH_MODE"] = "token"


def _join_advice(address: str, error: BaseException) -> str:
    """One line: why joining the cluster at ``address`` failed and what to do."""
    cause = " ".join(str(error).split())
    mode = os.environ.get("RAY_AUTH_MODE", "unset")
    return (
        f"cannot join the Ray cluster at {address} ({cause}; RAY_AUTH_MODE {mode}). A cluster started with `ray start` "
        "on Ray >= 2.59 asks for its token: copy the head node's ~/.ray/auth_token to this machine's ~/.ray/ (or set "
        "RAY_AUTH_TOKEN or RAY_AUTH_TOKEN_PATH). Otherwise check that the address is the one `ray start --head` "
        "printed and that its port is reachable from here"
    )
