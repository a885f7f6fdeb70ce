"""The fleet's processes: the merge service, the vehicle agent, the service's store and the
multi-robot demo that runs them on loopback.

May import: mergesvc.core, mergesvc.wire, mergesvc.link, mergesvc.sim, mergesvc.errors.
"""
