"""What a run hands on: the per-tree table, its metrics and files, where its numbers come
from (provenance) and the checks it passes or fails; the report, the stream and the store
read them."""
