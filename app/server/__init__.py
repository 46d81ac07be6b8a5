"""The console server: FastAPI on one public port, Viser behind it on loopback."""
