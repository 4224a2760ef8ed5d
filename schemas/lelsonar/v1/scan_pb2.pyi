from lelsonar.v1 import common_pb2 as _common_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class RotationDirection(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    ROTATION_DIRECTION_UNSPECIFIED: _ClassVar[RotationDirection]
    ROTATION_DIRECTION_INCREASING: _ClassVar[RotationDirection]
    ROTATION_DIRECTION_DECREASING: _ClassVar[RotationDirection]

class WaveformEncoding(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    WAVEFORM_ENCODING_UNSPECIFIED: _ClassVar[WaveformEncoding]
    WAVEFORM_ENCODING_FLOAT32_LE: _ClassVar[WaveformEncoding]
    WAVEFORM_ENCODING_INT16_LE: _ClassVar[WaveformEncoding]

class ScanStatus(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    SCAN_STATUS_UNSPECIFIED: _ClassVar[ScanStatus]
    SCAN_STATUS_COMPLETE: _ClassVar[ScanStatus]
    SCAN_STATUS_ABORTED: _ClassVar[ScanStatus]
ROTATION_DIRECTION_UNSPECIFIED: RotationDirection
ROTATION_DIRECTION_INCREASING: RotationDirection
ROTATION_DIRECTION_DECREASING: RotationDirection
WAVEFORM_ENCODING_UNSPECIFIED: WaveformEncoding
WAVEFORM_ENCODING_FLOAT32_LE: WaveformEncoding
WAVEFORM_ENCODING_INT16_LE: WaveformEncoding
SCAN_STATUS_UNSPECIFIED: ScanStatus
SCAN_STATUS_COMPLETE: ScanStatus
SCAN_STATUS_ABORTED: ScanStatus

class Capsule(_message.Message):
    __slots__ = ("capsule_id", "position", "boresight")
    CAPSULE_ID_FIELD_NUMBER: _ClassVar[int]
    POSITION_FIELD_NUMBER: _ClassVar[int]
    BORESIGHT_FIELD_NUMBER: _ClassVar[int]
    capsule_id: int
    position: _common_pb2.Vector3
    boresight: _common_pb2.Vector3
    def __init__(self, capsule_id: _Optional[int] = ..., position: _Optional[_Union[_common_pb2.Vector3, _Mapping]] = ..., boresight: _Optional[_Union[_common_pb2.Vector3, _Mapping]] = ...) -> None: ...

class EnergyModel(_message.Message):
    __slots__ = ("phi0", "phi1", "phi2", "valid_min_range", "valid_max_range", "distance_unit", "energy_unit")
    PHI0_FIELD_NUMBER: _ClassVar[int]
    PHI1_FIELD_NUMBER: _ClassVar[int]
    PHI2_FIELD_NUMBER: _ClassVar[int]
    VALID_MIN_RANGE_FIELD_NUMBER: _ClassVar[int]
    VALID_MAX_RANGE_FIELD_NUMBER: _ClassVar[int]
    DISTANCE_UNIT_FIELD_NUMBER: _ClassVar[int]
    ENERGY_UNIT_FIELD_NUMBER: _ClassVar[int]
    phi0: float
    phi1: float
    phi2: float
    valid_min_range: float
    valid_max_range: float
    distance_unit: str
    energy_unit: str
    def __init__(self, phi0: _Optional[float] = ..., phi1: _Optional[float] = ..., phi2: _Optional[float] = ..., valid_min_range: _Optional[float] = ..., valid_max_range: _Optional[float] = ..., distance_unit: _Optional[str] = ..., energy_unit: _Optional[str] = ...) -> None: ...

class ScanStart(_message.Message):
    __slots__ = ("schema_version", "scanner_id", "scan_id", "start_time_ns", "software_version", "capsules", "rotation_axis", "radial_offset", "gamma_start", "gamma_stop", "steps", "direction", "sound_speed", "air_temperature", "sample_rate", "window_samples", "energy_model", "device", "pose")
    SCHEMA_VERSION_FIELD_NUMBER: _ClassVar[int]
    SCANNER_ID_FIELD_NUMBER: _ClassVar[int]
    SCAN_ID_FIELD_NUMBER: _ClassVar[int]
    START_TIME_NS_FIELD_NUMBER: _ClassVar[int]
    SOFTWARE_VERSION_FIELD_NUMBER: _ClassVar[int]
    CAPSULES_FIELD_NUMBER: _ClassVar[int]
    ROTATION_AXIS_FIELD_NUMBER: _ClassVar[int]
    RADIAL_OFFSET_FIELD_NUMBER: _ClassVar[int]
    GAMMA_START_FIELD_NUMBER: _ClassVar[int]
    GAMMA_STOP_FIELD_NUMBER: _ClassVar[int]
    STEPS_FIELD_NUMBER: _ClassVar[int]
    DIRECTION_FIELD_NUMBER: _ClassVar[int]
    SOUND_SPEED_FIELD_NUMBER: _ClassVar[int]
    AIR_TEMPERATURE_FIELD_NUMBER: _ClassVar[int]
    SAMPLE_RATE_FIELD_NUMBER: _ClassVar[int]
    WINDOW_SAMPLES_FIELD_NUMBER: _ClassVar[int]
    ENERGY_MODEL_FIELD_NUMBER: _ClassVar[int]
    DEVICE_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    schema_version: int
    scanner_id: str
    scan_id: int
    start_time_ns: int
    software_version: str
    capsules: _containers.RepeatedCompositeFieldContainer[Capsule]
    rotation_axis: _common_pb2.Vector3
    radial_offset: float
    gamma_start: float
    gamma_stop: float
    steps: int
    direction: RotationDirection
    sound_speed: float
    air_temperature: float
    sample_rate: float
    window_samples: int
    energy_model: EnergyModel
    device: str
    pose: PoseWithCovariance
    def __init__(self, schema_version: _Optional[int] = ..., scanner_id: _Optional[str] = ..., scan_id: _Optional[int] = ..., start_time_ns: _Optional[int] = ..., software_version: _Optional[str] = ..., capsules: _Optional[_Iterable[_Union[Capsule, _Mapping]]] = ..., rotation_axis: _Optional[_Union[_common_pb2.Vector3, _Mapping]] = ..., radial_offset: _Optional[float] = ..., gamma_start: _Optional[float] = ..., gamma_stop: _Optional[float] = ..., steps: _Optional[int] = ..., direction: _Optional[_Union[RotationDirection, str]] = ..., sound_speed: _Optional[float] = ..., air_temperature: _Optional[float] = ..., sample_rate: _Optional[float] = ..., window_samples: _Optional[int] = ..., energy_model: _Optional[_Union[EnergyModel, _Mapping]] = ..., device: _Optional[str] = ..., pose: _Optional[_Union[PoseWithCovariance, _Mapping]] = ...) -> None: ...

class Quaternion(_message.Message):
    __slots__ = ("x", "y", "z", "w")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    W_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    z: float
    w: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., z: _Optional[float] = ..., w: _Optional[float] = ...) -> None: ...

class PoseWithCovariance(_message.Message):
    __slots__ = ("frame_id", "position", "orientation", "covariance")
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    POSITION_FIELD_NUMBER: _ClassVar[int]
    ORIENTATION_FIELD_NUMBER: _ClassVar[int]
    COVARIANCE_FIELD_NUMBER: _ClassVar[int]
    frame_id: str
    position: _common_pb2.Vector3
    orientation: Quaternion
    covariance: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, frame_id: _Optional[str] = ..., position: _Optional[_Union[_common_pb2.Vector3, _Mapping]] = ..., orientation: _Optional[_Union[Quaternion, _Mapping]] = ..., covariance: _Optional[_Iterable[float]] = ...) -> None: ...

class Odometry(_message.Message):
    __slots__ = ("schema_version", "scanner_id", "time_ns", "pose")
    SCHEMA_VERSION_FIELD_NUMBER: _ClassVar[int]
    SCANNER_ID_FIELD_NUMBER: _ClassVar[int]
    TIME_NS_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    schema_version: int
    scanner_id: str
    time_ns: int
    pose: PoseWithCovariance
    def __init__(self, schema_version: _Optional[int] = ..., scanner_id: _Optional[str] = ..., time_ns: _Optional[int] = ..., pose: _Optional[_Union[PoseWithCovariance, _Mapping]] = ...) -> None: ...

class MotorStatus(_message.Message):
    __slots__ = ("present_position_raw", "load", "voltage", "temperature", "error_bits")
    PRESENT_POSITION_RAW_FIELD_NUMBER: _ClassVar[int]
    LOAD_FIELD_NUMBER: _ClassVar[int]
    VOLTAGE_FIELD_NUMBER: _ClassVar[int]
    TEMPERATURE_FIELD_NUMBER: _ClassVar[int]
    ERROR_BITS_FIELD_NUMBER: _ClassVar[int]
    present_position_raw: int
    load: float
    voltage: float
    temperature: float
    error_bits: int
    def __init__(self, present_position_raw: _Optional[int] = ..., load: _Optional[float] = ..., voltage: _Optional[float] = ..., temperature: _Optional[float] = ..., error_bits: _Optional[int] = ...) -> None: ...

class Waveform(_message.Message):
    __slots__ = ("encoding", "data", "scale", "sample_rate", "t0", "sample_count")
    ENCODING_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    SCALE_FIELD_NUMBER: _ClassVar[int]
    SAMPLE_RATE_FIELD_NUMBER: _ClassVar[int]
    T0_FIELD_NUMBER: _ClassVar[int]
    SAMPLE_COUNT_FIELD_NUMBER: _ClassVar[int]
    encoding: WaveformEncoding
    data: bytes
    scale: float
    sample_rate: float
    t0: float
    sample_count: int
    def __init__(self, encoding: _Optional[_Union[WaveformEncoding, str]] = ..., data: _Optional[bytes] = ..., scale: _Optional[float] = ..., sample_rate: _Optional[float] = ..., t0: _Optional[float] = ..., sample_count: _Optional[int] = ...) -> None: ...

class SensorReading(_message.Message):
    __slots__ = ("capsule_id", "echo_valid", "time_of_flight", "distance", "waveform")
    CAPSULE_ID_FIELD_NUMBER: _ClassVar[int]
    ECHO_VALID_FIELD_NUMBER: _ClassVar[int]
    TIME_OF_FLIGHT_FIELD_NUMBER: _ClassVar[int]
    DISTANCE_FIELD_NUMBER: _ClassVar[int]
    WAVEFORM_FIELD_NUMBER: _ClassVar[int]
    capsule_id: int
    echo_valid: bool
    time_of_flight: float
    distance: float
    waveform: Waveform
    def __init__(self, capsule_id: _Optional[int] = ..., echo_valid: _Optional[bool] = ..., time_of_flight: _Optional[float] = ..., distance: _Optional[float] = ..., waveform: _Optional[_Union[Waveform, _Mapping]] = ...) -> None: ...

class Sample(_message.Message):
    __slots__ = ("schema_version", "scanner_id", "scan_id", "step", "acquisition_time_ns", "gamma_commanded", "gamma_measured", "motor", "sensors", "sensor_energy")
    SCHEMA_VERSION_FIELD_NUMBER: _ClassVar[int]
    SCANNER_ID_FIELD_NUMBER: _ClassVar[int]
    SCAN_ID_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    ACQUISITION_TIME_NS_FIELD_NUMBER: _ClassVar[int]
    GAMMA_COMMANDED_FIELD_NUMBER: _ClassVar[int]
    GAMMA_MEASURED_FIELD_NUMBER: _ClassVar[int]
    MOTOR_FIELD_NUMBER: _ClassVar[int]
    SENSORS_FIELD_NUMBER: _ClassVar[int]
    SENSOR_ENERGY_FIELD_NUMBER: _ClassVar[int]
    schema_version: int
    scanner_id: str
    scan_id: int
    step: int
    acquisition_time_ns: int
    gamma_commanded: float
    gamma_measured: float
    motor: MotorStatus
    sensors: _containers.RepeatedCompositeFieldContainer[SensorReading]
    sensor_energy: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, schema_version: _Optional[int] = ..., scanner_id: _Optional[str] = ..., scan_id: _Optional[int] = ..., step: _Optional[int] = ..., acquisition_time_ns: _Optional[int] = ..., gamma_commanded: _Optional[float] = ..., gamma_measured: _Optional[float] = ..., motor: _Optional[_Union[MotorStatus, _Mapping]] = ..., sensors: _Optional[_Iterable[_Union[SensorReading, _Mapping]]] = ..., sensor_energy: _Optional[_Iterable[float]] = ...) -> None: ...

class ScanEnd(_message.Message):
    __slots__ = ("schema_version", "scanner_id", "scan_id", "end_time_ns", "status", "reason", "steps_planned", "samples_sent", "echoes_missing")
    SCHEMA_VERSION_FIELD_NUMBER: _ClassVar[int]
    SCANNER_ID_FIELD_NUMBER: _ClassVar[int]
    SCAN_ID_FIELD_NUMBER: _ClassVar[int]
    END_TIME_NS_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    STEPS_PLANNED_FIELD_NUMBER: _ClassVar[int]
    SAMPLES_SENT_FIELD_NUMBER: _ClassVar[int]
    ECHOES_MISSING_FIELD_NUMBER: _ClassVar[int]
    schema_version: int
    scanner_id: str
    scan_id: int
    end_time_ns: int
    status: ScanStatus
    reason: str
    steps_planned: int
    samples_sent: int
    echoes_missing: int
    def __init__(self, schema_version: _Optional[int] = ..., scanner_id: _Optional[str] = ..., scan_id: _Optional[int] = ..., end_time_ns: _Optional[int] = ..., status: _Optional[_Union[ScanStatus, str]] = ..., reason: _Optional[str] = ..., steps_planned: _Optional[int] = ..., samples_sent: _Optional[int] = ..., echoes_missing: _Optional[int] = ...) -> None: ...
