from lelsonar.v1 import common_pb2 as _common_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class PlaneQuality(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    PLANE_QUALITY_UNSPECIFIED: _ClassVar[PlaneQuality]
    PLANE_QUALITY_GOOD: _ClassVar[PlaneQuality]
    PLANE_QUALITY_DEGRADED: _ClassVar[PlaneQuality]
    PLANE_QUALITY_UNRELIABLE: _ClassVar[PlaneQuality]

class EstimateStatus(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    ESTIMATE_STATUS_UNSPECIFIED: _ClassVar[EstimateStatus]
    ESTIMATE_STATUS_PROVISIONAL: _ClassVar[EstimateStatus]
    ESTIMATE_STATUS_FINAL: _ClassVar[EstimateStatus]
    ESTIMATE_STATUS_FINAL_TIMEOUT: _ClassVar[EstimateStatus]
    ESTIMATE_STATUS_INCOMPLETE: _ClassVar[EstimateStatus]
    ESTIMATE_STATUS_ABORTED: _ClassVar[EstimateStatus]
PLANE_QUALITY_UNSPECIFIED: PlaneQuality
PLANE_QUALITY_GOOD: PlaneQuality
PLANE_QUALITY_DEGRADED: PlaneQuality
PLANE_QUALITY_UNRELIABLE: PlaneQuality
ESTIMATE_STATUS_UNSPECIFIED: EstimateStatus
ESTIMATE_STATUS_PROVISIONAL: EstimateStatus
ESTIMATE_STATUS_FINAL: EstimateStatus
ESTIMATE_STATUS_FINAL_TIMEOUT: EstimateStatus
ESTIMATE_STATUS_INCOMPLETE: EstimateStatus
ESTIMATE_STATUS_ABORTED: EstimateStatus

class PlaneEstimate(_message.Message):
    __slots__ = ("label", "method", "normal", "offset", "theta", "sigma_relative", "sigma", "inlier_count", "point_count", "lel_cost", "theta_covariance", "normal_stderr", "offset_stderr", "patch", "quality", "quality_reasons")
    LABEL_FIELD_NUMBER: _ClassVar[int]
    METHOD_FIELD_NUMBER: _ClassVar[int]
    NORMAL_FIELD_NUMBER: _ClassVar[int]
    OFFSET_FIELD_NUMBER: _ClassVar[int]
    THETA_FIELD_NUMBER: _ClassVar[int]
    SIGMA_RELATIVE_FIELD_NUMBER: _ClassVar[int]
    SIGMA_FIELD_NUMBER: _ClassVar[int]
    INLIER_COUNT_FIELD_NUMBER: _ClassVar[int]
    POINT_COUNT_FIELD_NUMBER: _ClassVar[int]
    LEL_COST_FIELD_NUMBER: _ClassVar[int]
    THETA_COVARIANCE_FIELD_NUMBER: _ClassVar[int]
    NORMAL_STDERR_FIELD_NUMBER: _ClassVar[int]
    OFFSET_STDERR_FIELD_NUMBER: _ClassVar[int]
    PATCH_FIELD_NUMBER: _ClassVar[int]
    QUALITY_FIELD_NUMBER: _ClassVar[int]
    QUALITY_REASONS_FIELD_NUMBER: _ClassVar[int]
    label: str
    method: str
    normal: _common_pb2.Vector3
    offset: float
    theta: _common_pb2.Vector3
    sigma_relative: float
    sigma: float
    inlier_count: int
    point_count: int
    lel_cost: float
    theta_covariance: _containers.RepeatedScalarFieldContainer[float]
    normal_stderr: float
    offset_stderr: float
    patch: _containers.RepeatedCompositeFieldContainer[_common_pb2.Vector3]
    quality: PlaneQuality
    quality_reasons: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, label: _Optional[str] = ..., method: _Optional[str] = ..., normal: _Optional[_Union[_common_pb2.Vector3, _Mapping]] = ..., offset: _Optional[float] = ..., theta: _Optional[_Union[_common_pb2.Vector3, _Mapping]] = ..., sigma_relative: _Optional[float] = ..., sigma: _Optional[float] = ..., inlier_count: _Optional[int] = ..., point_count: _Optional[int] = ..., lel_cost: _Optional[float] = ..., theta_covariance: _Optional[_Iterable[float]] = ..., normal_stderr: _Optional[float] = ..., offset_stderr: _Optional[float] = ..., patch: _Optional[_Iterable[_Union[_common_pb2.Vector3, _Mapping]]] = ..., quality: _Optional[_Union[PlaneQuality, str]] = ..., quality_reasons: _Optional[_Iterable[str]] = ...) -> None: ...

class Line(_message.Message):
    __slots__ = ("point", "direction", "point_stderr", "direction_stderr")
    POINT_FIELD_NUMBER: _ClassVar[int]
    DIRECTION_FIELD_NUMBER: _ClassVar[int]
    POINT_STDERR_FIELD_NUMBER: _ClassVar[int]
    DIRECTION_STDERR_FIELD_NUMBER: _ClassVar[int]
    point: _common_pb2.Vector3
    direction: _common_pb2.Vector3
    point_stderr: float
    direction_stderr: float
    def __init__(self, point: _Optional[_Union[_common_pb2.Vector3, _Mapping]] = ..., direction: _Optional[_Union[_common_pb2.Vector3, _Mapping]] = ..., point_stderr: _Optional[float] = ..., direction_stderr: _Optional[float] = ...) -> None: ...

class SurfaceEstimate(_message.Message):
    __slots__ = ("label", "plane", "bearing", "tilt", "covariance", "bearing_source", "echo_count")
    LABEL_FIELD_NUMBER: _ClassVar[int]
    PLANE_FIELD_NUMBER: _ClassVar[int]
    BEARING_FIELD_NUMBER: _ClassVar[int]
    TILT_FIELD_NUMBER: _ClassVar[int]
    COVARIANCE_FIELD_NUMBER: _ClassVar[int]
    BEARING_SOURCE_FIELD_NUMBER: _ClassVar[int]
    ECHO_COUNT_FIELD_NUMBER: _ClassVar[int]
    label: str
    plane: PlaneEstimate
    bearing: float
    tilt: float
    covariance: _containers.RepeatedScalarFieldContainer[float]
    bearing_source: str
    echo_count: int
    def __init__(self, label: _Optional[str] = ..., plane: _Optional[_Union[PlaneEstimate, _Mapping]] = ..., bearing: _Optional[float] = ..., tilt: _Optional[float] = ..., covariance: _Optional[_Iterable[float]] = ..., bearing_source: _Optional[str] = ..., echo_count: _Optional[int] = ...) -> None: ...

class FeatureEstimate(_message.Message):
    __slots__ = ("label", "line", "covariance", "surfaces", "reasons", "echo_count")
    LABEL_FIELD_NUMBER: _ClassVar[int]
    LINE_FIELD_NUMBER: _ClassVar[int]
    COVARIANCE_FIELD_NUMBER: _ClassVar[int]
    SURFACES_FIELD_NUMBER: _ClassVar[int]
    REASONS_FIELD_NUMBER: _ClassVar[int]
    ECHO_COUNT_FIELD_NUMBER: _ClassVar[int]
    label: str
    line: Line
    covariance: _containers.RepeatedScalarFieldContainer[float]
    surfaces: _containers.RepeatedScalarFieldContainer[str]
    reasons: _containers.RepeatedScalarFieldContainer[str]
    echo_count: int
    def __init__(self, label: _Optional[str] = ..., line: _Optional[_Union[Line, _Mapping]] = ..., covariance: _Optional[_Iterable[float]] = ..., surfaces: _Optional[_Iterable[str]] = ..., reasons: _Optional[_Iterable[str]] = ..., echo_count: _Optional[int] = ...) -> None: ...

class UnexplainedEchoes(_message.Message):
    __slots__ = ("cause", "count")
    CAUSE_FIELD_NUMBER: _ClassVar[int]
    COUNT_FIELD_NUMBER: _ClassVar[int]
    cause: str
    count: int
    def __init__(self, cause: _Optional[str] = ..., count: _Optional[int] = ...) -> None: ...

class ComputeTimings(_message.Message):
    __slots__ = ("segmentation", "fit", "total")
    SEGMENTATION_FIELD_NUMBER: _ClassVar[int]
    FIT_FIELD_NUMBER: _ClassVar[int]
    TOTAL_FIELD_NUMBER: _ClassVar[int]
    segmentation: float
    fit: float
    total: float
    def __init__(self, segmentation: _Optional[float] = ..., fit: _Optional[float] = ..., total: _Optional[float] = ...) -> None: ...

class ScanAccounting(_message.Message):
    __slots__ = ("published", "received_live", "recovered", "duplicates", "rejected", "missing", "conflicts")
    class RejectedEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: int
        def __init__(self, key: _Optional[str] = ..., value: _Optional[int] = ...) -> None: ...
    PUBLISHED_FIELD_NUMBER: _ClassVar[int]
    RECEIVED_LIVE_FIELD_NUMBER: _ClassVar[int]
    RECOVERED_FIELD_NUMBER: _ClassVar[int]
    DUPLICATES_FIELD_NUMBER: _ClassVar[int]
    REJECTED_FIELD_NUMBER: _ClassVar[int]
    MISSING_FIELD_NUMBER: _ClassVar[int]
    CONFLICTS_FIELD_NUMBER: _ClassVar[int]
    published: int
    received_live: int
    recovered: int
    duplicates: int
    rejected: _containers.ScalarMap[str, int]
    missing: int
    conflicts: int
    def __init__(self, published: _Optional[int] = ..., received_live: _Optional[int] = ..., recovered: _Optional[int] = ..., duplicates: _Optional[int] = ..., rejected: _Optional[_Mapping[str, int]] = ..., missing: _Optional[int] = ..., conflicts: _Optional[int] = ...) -> None: ...

class Reconstruction(_message.Message):
    __slots__ = ("schema_version", "scanner_id", "scan_id", "last_step", "status", "stamp_ns", "critical_step", "critical_angle", "planes", "corner_edge", "timings", "samples_used", "failures", "missing_steps", "accounting", "revision", "aborted_reason", "surfaces", "corners", "edges", "unexplained", "surface_echo_count")
    SCHEMA_VERSION_FIELD_NUMBER: _ClassVar[int]
    SCANNER_ID_FIELD_NUMBER: _ClassVar[int]
    SCAN_ID_FIELD_NUMBER: _ClassVar[int]
    LAST_STEP_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    CRITICAL_STEP_FIELD_NUMBER: _ClassVar[int]
    CRITICAL_ANGLE_FIELD_NUMBER: _ClassVar[int]
    PLANES_FIELD_NUMBER: _ClassVar[int]
    CORNER_EDGE_FIELD_NUMBER: _ClassVar[int]
    TIMINGS_FIELD_NUMBER: _ClassVar[int]
    SAMPLES_USED_FIELD_NUMBER: _ClassVar[int]
    FAILURES_FIELD_NUMBER: _ClassVar[int]
    MISSING_STEPS_FIELD_NUMBER: _ClassVar[int]
    ACCOUNTING_FIELD_NUMBER: _ClassVar[int]
    REVISION_FIELD_NUMBER: _ClassVar[int]
    ABORTED_REASON_FIELD_NUMBER: _ClassVar[int]
    SURFACES_FIELD_NUMBER: _ClassVar[int]
    CORNERS_FIELD_NUMBER: _ClassVar[int]
    EDGES_FIELD_NUMBER: _ClassVar[int]
    UNEXPLAINED_FIELD_NUMBER: _ClassVar[int]
    SURFACE_ECHO_COUNT_FIELD_NUMBER: _ClassVar[int]
    schema_version: int
    scanner_id: str
    scan_id: int
    last_step: int
    status: EstimateStatus
    stamp_ns: int
    critical_step: int
    critical_angle: float
    planes: _containers.RepeatedCompositeFieldContainer[PlaneEstimate]
    corner_edge: Line
    timings: ComputeTimings
    samples_used: int
    failures: _containers.RepeatedScalarFieldContainer[str]
    missing_steps: _containers.RepeatedScalarFieldContainer[int]
    accounting: ScanAccounting
    revision: int
    aborted_reason: str
    surfaces: _containers.RepeatedCompositeFieldContainer[SurfaceEstimate]
    corners: _containers.RepeatedCompositeFieldContainer[FeatureEstimate]
    edges: _containers.RepeatedCompositeFieldContainer[FeatureEstimate]
    unexplained: _containers.RepeatedCompositeFieldContainer[UnexplainedEchoes]
    surface_echo_count: int
    def __init__(self, schema_version: _Optional[int] = ..., scanner_id: _Optional[str] = ..., scan_id: _Optional[int] = ..., last_step: _Optional[int] = ..., status: _Optional[_Union[EstimateStatus, str]] = ..., stamp_ns: _Optional[int] = ..., critical_step: _Optional[int] = ..., critical_angle: _Optional[float] = ..., planes: _Optional[_Iterable[_Union[PlaneEstimate, _Mapping]]] = ..., corner_edge: _Optional[_Union[Line, _Mapping]] = ..., timings: _Optional[_Union[ComputeTimings, _Mapping]] = ..., samples_used: _Optional[int] = ..., failures: _Optional[_Iterable[str]] = ..., missing_steps: _Optional[_Iterable[int]] = ..., accounting: _Optional[_Union[ScanAccounting, _Mapping]] = ..., revision: _Optional[int] = ..., aborted_reason: _Optional[str] = ..., surfaces: _Optional[_Iterable[_Union[SurfaceEstimate, _Mapping]]] = ..., corners: _Optional[_Iterable[_Union[FeatureEstimate, _Mapping]]] = ..., edges: _Optional[_Iterable[_Union[FeatureEstimate, _Mapping]]] = ..., unexplained: _Optional[_Iterable[_Union[UnexplainedEchoes, _Mapping]]] = ..., surface_echo_count: _Optional[int] = ...) -> None: ...
