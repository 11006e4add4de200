"""Object storage: output roots in a bucket (s3://, gs://, file://) mirrored on local disk.

Modules: `filesystems` (one fsspec filesystem per protocol, object paths, write probes), `publish` (staging, copy,
publication record last; pulling what is published), `reads` (ranged reads of shards left in the bucket), `locks`
(an output's local lock plus its lock object in the bucket). Where a bucket is mounted on disk:
`steering_core.storage.mirrors`.
"""
