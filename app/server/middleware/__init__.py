"""What every request to the console passes through before a route: authentication and
Origin checks (auth.py), request body limits (limits.py), connection limits on the public
port (connections.py)."""
