"""Generated gRPC stubs for relreward.v1 (built from proto/ when the package is built).

Private: import the public API from ``relreward``. The message classes are reachable as
``relreward.pb`` for callers that need a raw message.
"""
