"""The console's HTTP side: the FastAPI application, its REST routers, authentication, request and
connection limits, the Viser relay.
"""
