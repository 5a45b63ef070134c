"""A collection in one command: many captures reconstructed on Dask's distributed scheduler.

Owns finding the captures and reading a manifest (:mod:`.sources`), the rows of ``batch.csv``
(:mod:`.rows`), one object in a worker with its fingerprint for resuming (:mod:`.runner`), the
cluster, lock and tasks (:mod:`.scheduler`), and the gallery page ``index.html`` (:mod:`.gallery`).
``docs/cluster.md`` runs a batch on several machines.
"""

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach(
    __name__,
    submod_attrs={
        "gallery": ["write_index", "write_thumbnails"],
        "rows": ["BatchItem", "BatchRow", "write_rows"],
        "runner": ["BatchStopped", "choose_workers", "describe_failure", "estimate_peak_mb", "fingerprint",
                   "is_complete", "run_object", "stop_objects"],
        "scheduler": ["batch_lock", "collect_items", "run_batch"],
        "sources": ["discover", "read_manifest"],
    },
)
