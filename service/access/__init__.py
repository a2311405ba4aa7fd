"""Who may do what: API keys (keys.py, managed by ``blendsplat keys``: keys_cli.py), principals, tenants, scopes and
the audit (auth.py), per-key limits (limits.py), and the HTTP side of them: the bearer dependency every route
declares and the WebSocket's key and Origin check (http.py)."""
