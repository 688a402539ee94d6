"""The store: how dali keeps data on disk.

Owns the artifact formats (frame sets in zarr, box tables in Parquet, JSON side files), the
manifest that makes every stage atomic and incremental, output-path ownership and locking,
content hashes, frame ids, the scale file and the model card.

May import: the standard library, numpy, zarr, pyarrow, and ``dali_cli.runtime`` (errors,
console). Nothing else in dali_cli: every other layer builds on this one.
"""
