"""Serving a trained policy: the model (``model/``, torch), checkpoints, the per-view composition
(``aggregation``), the denoising workers, the gRPC server and the robot-side client (numpy and
grpc only)."""

POLICY_PROTO_VERSION = 1  # proto/services/pb/policy.proto: bump on a change clients must know about
