from lelsonar.v1 import common_pb2 as _common_pb2
from lelsonar.v1 import reconstruction_pb2 as _reconstruction_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class MapWall(_message.Message):
    __slots__ = ("id", "normal", "offset", "extent", "covariance", "normal_stderr", "offset_stderr", "quality", "quality_reasons", "scan_ids", "good_observations", "flagged_observations", "pieces", "piece_scans")
    ID_FIELD_NUMBER: _ClassVar[int]
    NORMAL_FIELD_NUMBER: _ClassVar[int]
    OFFSET_FIELD_NUMBER: _ClassVar[int]
    EXTENT_FIELD_NUMBER: _ClassVar[int]
    COVARIANCE_FIELD_NUMBER: _ClassVar[int]
    NORMAL_STDERR_FIELD_NUMBER: _ClassVar[int]
    OFFSET_STDERR_FIELD_NUMBER: _ClassVar[int]
    QUALITY_FIELD_NUMBER: _ClassVar[int]
    QUALITY_REASONS_FIELD_NUMBER: _ClassVar[int]
    SCAN_IDS_FIELD_NUMBER: _ClassVar[int]
    GOOD_OBSERVATIONS_FIELD_NUMBER: _ClassVar[int]
    FLAGGED_OBSERVATIONS_FIELD_NUMBER: _ClassVar[int]
    PIECES_FIELD_NUMBER: _ClassVar[int]
    PIECE_SCANS_FIELD_NUMBER: _ClassVar[int]
    id: int
    normal: _common_pb2.Vector3
    offset: float
    extent: _containers.RepeatedCompositeFieldContainer[_common_pb2.Vector3]
    covariance: _containers.RepeatedScalarFieldContainer[float]
    normal_stderr: float
    offset_stderr: float
    quality: _reconstruction_pb2.PlaneQuality
    quality_reasons: _containers.RepeatedScalarFieldContainer[str]
    scan_ids: _containers.RepeatedScalarFieldContainer[int]
    good_observations: int
    flagged_observations: int
    pieces: _containers.RepeatedCompositeFieldContainer[_common_pb2.Vector3]
    piece_scans: _containers.RepeatedCompositeFieldContainer[MapPieceScans]
    def __init__(self, id: _Optional[int] = ..., normal: _Optional[_Union[_common_pb2.Vector3, _Mapping]] = ..., offset: _Optional[float] = ..., extent: _Optional[_Iterable[_Union[_common_pb2.Vector3, _Mapping]]] = ..., covariance: _Optional[_Iterable[float]] = ..., normal_stderr: _Optional[float] = ..., offset_stderr: _Optional[float] = ..., quality: _Optional[_Union[_reconstruction_pb2.PlaneQuality, str]] = ..., quality_reasons: _Optional[_Iterable[str]] = ..., scan_ids: _Optional[_Iterable[int]] = ..., good_observations: _Optional[int] = ..., flagged_observations: _Optional[int] = ..., pieces: _Optional[_Iterable[_Union[_common_pb2.Vector3, _Mapping]]] = ..., piece_scans: _Optional[_Iterable[_Union[MapPieceScans, _Mapping]]] = ...) -> None: ...

class MapPieceScans(_message.Message):
    __slots__ = ("scan_ids",)
    SCAN_IDS_FIELD_NUMBER: _ClassVar[int]
    scan_ids: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, scan_ids: _Optional[_Iterable[int]] = ...) -> None: ...

class MapFeature(_message.Message):
    __slots__ = ("point", "direction", "kind", "point_stderr", "observations", "wall_ids", "source", "scan_ids")
    POINT_FIELD_NUMBER: _ClassVar[int]
    DIRECTION_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    POINT_STDERR_FIELD_NUMBER: _ClassVar[int]
    OBSERVATIONS_FIELD_NUMBER: _ClassVar[int]
    WALL_IDS_FIELD_NUMBER: _ClassVar[int]
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    SCAN_IDS_FIELD_NUMBER: _ClassVar[int]
    point: _common_pb2.Vector3
    direction: _common_pb2.Vector3
    kind: str
    point_stderr: float
    observations: int
    wall_ids: _containers.RepeatedScalarFieldContainer[int]
    source: str
    scan_ids: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, point: _Optional[_Union[_common_pb2.Vector3, _Mapping]] = ..., direction: _Optional[_Union[_common_pb2.Vector3, _Mapping]] = ..., kind: _Optional[str] = ..., point_stderr: _Optional[float] = ..., observations: _Optional[int] = ..., wall_ids: _Optional[_Iterable[int]] = ..., source: _Optional[str] = ..., scan_ids: _Optional[_Iterable[int]] = ...) -> None: ...

class MapPose(_message.Message):
    __slots__ = ("scan_id", "position", "heading", "covariance", "odometry")
    SCAN_ID_FIELD_NUMBER: _ClassVar[int]
    POSITION_FIELD_NUMBER: _ClassVar[int]
    HEADING_FIELD_NUMBER: _ClassVar[int]
    COVARIANCE_FIELD_NUMBER: _ClassVar[int]
    ODOMETRY_FIELD_NUMBER: _ClassVar[int]
    scan_id: int
    position: _common_pb2.Vector3
    heading: float
    covariance: _containers.RepeatedScalarFieldContainer[float]
    odometry: _common_pb2.Vector3
    def __init__(self, scan_id: _Optional[int] = ..., position: _Optional[_Union[_common_pb2.Vector3, _Mapping]] = ..., heading: _Optional[float] = ..., covariance: _Optional[_Iterable[float]] = ..., odometry: _Optional[_Union[_common_pb2.Vector3, _Mapping]] = ...) -> None: ...

class MapView(_message.Message):
    __slots__ = ("scan_id", "polygon")
    SCAN_ID_FIELD_NUMBER: _ClassVar[int]
    POLYGON_FIELD_NUMBER: _ClassVar[int]
    scan_id: int
    polygon: _containers.RepeatedCompositeFieldContainer[_common_pb2.Vector3]
    def __init__(self, scan_id: _Optional[int] = ..., polygon: _Optional[_Iterable[_Union[_common_pb2.Vector3, _Mapping]]] = ...) -> None: ...

class Map(_message.Message):
    __slots__ = ("schema_version", "scanner_id", "stamp_ns", "scans", "walls", "corners", "edges", "poses", "notes", "views", "horizontal_corners")
    SCHEMA_VERSION_FIELD_NUMBER: _ClassVar[int]
    SCANNER_ID_FIELD_NUMBER: _ClassVar[int]
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    SCANS_FIELD_NUMBER: _ClassVar[int]
    WALLS_FIELD_NUMBER: _ClassVar[int]
    CORNERS_FIELD_NUMBER: _ClassVar[int]
    EDGES_FIELD_NUMBER: _ClassVar[int]
    POSES_FIELD_NUMBER: _ClassVar[int]
    NOTES_FIELD_NUMBER: _ClassVar[int]
    VIEWS_FIELD_NUMBER: _ClassVar[int]
    HORIZONTAL_CORNERS_FIELD_NUMBER: _ClassVar[int]
    schema_version: int
    scanner_id: str
    stamp_ns: int
    scans: int
    walls: _containers.RepeatedCompositeFieldContainer[MapWall]
    corners: _containers.RepeatedCompositeFieldContainer[MapFeature]
    edges: _containers.RepeatedCompositeFieldContainer[MapFeature]
    poses: _containers.RepeatedCompositeFieldContainer[MapPose]
    notes: _containers.RepeatedScalarFieldContainer[str]
    views: _containers.RepeatedCompositeFieldContainer[MapView]
    horizontal_corners: _containers.RepeatedCompositeFieldContainer[MapFeature]
    def __init__(self, schema_version: _Optional[int] = ..., scanner_id: _Optional[str] = ..., stamp_ns: _Optional[int] = ..., scans: _Optional[int] = ..., walls: _Optional[_Iterable[_Union[MapWall, _Mapping]]] = ..., corners: _Optional[_Iterable[_Union[MapFeature, _Mapping]]] = ..., edges: _Optional[_Iterable[_Union[MapFeature, _Mapping]]] = ..., poses: _Optional[_Iterable[_Union[MapPose, _Mapping]]] = ..., notes: _Optional[_Iterable[str]] = ..., views: _Optional[_Iterable[_Union[MapView, _Mapping]]] = ..., horizontal_corners: _Optional[_Iterable[_Union[MapFeature, _Mapping]]] = ...) -> None: ...
