"""Persistence: the service's SQLite store (store/database.py), its records and schema
(store/records.py), the answers ledger beside it (store/acks.py) and a read-only view for other
processes (store/reader.py). Below fleet/ and bench/: both read it through this API."""

from mergesvc.store.acks import AckLedger
from mergesvc.store.database import CONFLICTS_KEPT, Store, is_memory
from mergesvc.store.reader import StoreReader
from mergesvc.store.records import (
    APPLICATION_ID,
    META_ANCHOR,
    META_EMBEDDING_DIM,
    META_FLEET,
    META_NOISE_SCALES,
    PENDING,
    STORE_SCHEMA_VERSION,
    StoredFactor,
    StoredFrame,
    StoredSubmap,
    SubmapConflictError,
    Synchronous,
)

__all__ = ["APPLICATION_ID", "CONFLICTS_KEPT", "META_ANCHOR", "META_EMBEDDING_DIM",
           "META_FLEET", "META_NOISE_SCALES", "PENDING", "STORE_SCHEMA_VERSION", "AckLedger",
           "Store", "StoreReader", "StoredFactor", "StoredFrame", "StoredSubmap",
           "SubmapConflictError", "Synchronous", "is_memory"]
