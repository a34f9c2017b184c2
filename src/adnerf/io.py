"""Video and audio I/O on PyAV (FFmpeg), with timestamps rather than assumed frame rates.

* :func:`read_video` decodes a video's frames (uint8 RGB, turned upright by the file's rotation
  metadata, as phones write portrait video), the exact presentation time of every frame, and
  optionally its audio track (mono float32, resampled on request). A file cut off mid-write
  gives the frames that decode and says where it ends.
* :func:`read_audio` decodes the audio of any file FFmpeg reads (wav, mp3, m4a, flac, mp4, ...).
* :class:`VideoWriter` encodes frames one at a time (h264) and an optional audio track (aac) into
  an mp4 with audio sample 0 at the time of frame 0, holding one frame in memory; it writes to a
  temporary file and renames it into place, so a failure leaves nothing partial.
  :func:`write_video` hands it an array of frames.

Timing convention: all times are seconds on the container's clock. Audio is returned together
with ``audio_start``, the time of its first sample; the AAC encoder's priming delay is removed
by the decoder through the mp4 edit list, and any remaining offset shows up in ``audio_start``,
which :mod:`adnerf.audio.features` uses to align audio windows with frame timestamps.

Every failure raises :class:`MediaError` naming the file and the problem.
"""

from __future__ import annotations

import sys
from contextlib import ExitStack
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from .atomic import atomic_path
from .memory import require

__all__ = ["AudioTrack", "FrameReader", "MediaError", "Video", "VideoWriter", "frame_times", "probe", "audio_span", "read_audio", "read_image", "read_rgb", "read_video", "write_video"]


class MediaError(RuntimeError):
    """A media file could not be read or written; the message names the file and the problem."""


def _av():
    try:
        import av
    except ImportError as exc:  # pragma: no cover - av is a core dependency
        raise MediaError("PyAV is not installed: pip install av") from exc
    return av


@dataclass
class AudioTrack:
    """Mono audio.

    Attributes:
        samples: float32 samples in ``[-1, 1]``, shape ``(n,)``.
        sample_rate: Samples per second.
        start: Time of the first sample in seconds (container clock; 0 for plain audio files).
    """

    samples: np.ndarray
    sample_rate: int
    start: float = 0.0

    @property
    def duration(self) -> float:
        """Length in seconds."""
        return len(self.samples) / self.sample_rate

    def starting_at(self, time: float) -> "AudioTrack":
        """The track from ``time`` (container clock) on, as a track whose sample 0 plays then
        (``start`` 0): cut where the track began earlier, led by silence where it began later."""
        skip = int(round((time - self.start) * self.sample_rate))
        samples = self.samples[skip:] if skip >= 0 else np.concatenate([np.zeros(-skip, self.samples.dtype), self.samples])
        return AudioTrack(samples, self.sample_rate, 0.0)


@dataclass
class Video:
    """A decoded video.

    Attributes:
        frames: uint8 RGB frames, shape ``(N, H, W, 3)``.
        timestamps: Presentation time of each frame in seconds, shape ``(N,)``, increasing.
        fps: Nominal frame rate reported by the container (informational: use ``timestamps``).
        audio: The audio track, or ``None`` when the file has none or it was not requested.
        rotation: Degrees the frames were turned clockwise to stand upright, from the file's
            display matrix (0, 90, 180 or 270; a portrait phone video gives 90).
        truncated: ``None``, or why decoding stopped before the end the file declares (a copy
            that did not finish): the frames are those that decoded.
    """

    frames: np.ndarray
    timestamps: np.ndarray
    fps: float
    audio: AudioTrack | None
    rotation: int = 0
    truncated: str | None = None


def _open(path: str | Path):
    av = _av()
    p = Path(path)
    if not p.exists():
        raise MediaError(f"{p}: no such file")
    if p.is_dir():
        raise MediaError(f"{p}: is a directory, not a media file")
    try:
        return av.open(str(p))
    except av.error.FFmpegError as exc:
        hint = ""
        if isinstance(exc, av.error.InvalidDataError) and p.suffix.lower() in (".mp4", ".mov", ".m4v", ".3gp"):
            # An mp4 writes its index (the moov box) last unless it was made for streaming: a copy
            # or recording that did not finish has frames but no index, and nothing can read it.
            hint = "; if the file is an unfinished copy or recording (its end, where an mp4 keeps its index, is missing), copy or export it again"
        raise MediaError(f"{p}: cannot open as media ({exc.strerror or exc}){hint}") from exc


def _upright_turns(path: Path, rotation: float) -> int:
    """Clockwise quarter turns that stand a frame upright, from FFmpeg's display rotation
    (degrees counterclockwise, as ``VideoFrame.rotation`` gives it)."""
    turns = -float(rotation) / 90.0
    if abs(turns - round(turns)) > 1e-3:
        raise MediaError(f"{path}: the file asks for a display rotation of {rotation:g} degrees; only quarter turns are supported")
    return int(round(turns)) % 4


def probe(path: str | Path) -> dict:
    """Stream summary of a media file: ``{"video": bool, "audio": bool, "fps": float|None,
    "duration": float|None, "sample_rate": int|None, "width": int|None, "height": int|None}``."""
    with _open(path) as container:
        v = container.streams.video[0] if container.streams.video else None
        a = container.streams.audio[0] if container.streams.audio else None
        return {
            "video": v is not None,
            "audio": a is not None,
            "fps": float(v.average_rate) if v is not None and v.average_rate else None,
            "duration": float(container.duration / 1_000_000) if container.duration else None,
            "sample_rate": a.rate if a is not None else None,
            "width": v.codec_context.width if v is not None else None,
            "height": v.codec_context.height if v is not None else None,
        }


def _video_stream(path: Path, container):
    """The first video stream of an open container, or a MediaError naming the file."""
    if not container.streams.video:
        raise MediaError(f"{path}: has no video stream")
    return container.streams.video[0]


def frame_times(path: str | Path) -> np.ndarray:
    """Presentation times (seconds, sorted) of every video frame, read from packets without decoding.

    Raises:
        MediaError: The file is missing or unreadable, or has no video stream.
    """
    av = _av()
    p = Path(path)
    with _open(p) as container:
        stream = _video_stream(p, container)
        times: list[float] = []
        try:
            for packet in container.demux(stream):
                if packet.pts is not None and packet.size > 0:
                    times.append(float(packet.pts * packet.time_base))
        except av.error.FFmpegError as exc:
            raise MediaError(f"{p}: cannot read the video stream ({exc.strerror or exc})") from exc
    if not times:
        raise MediaError(f"{p}: the video stream has no frames")
    return np.sort(np.asarray(times, dtype=np.float64))


class FrameReader:
    """A video's upright frames by index, in any order, decoded a chunk at a time.

    Frames are numbered in presentation order (as :func:`frame_times` lists them). Reading frame
    ``i`` decodes the chunk of ``chunk`` frames that holds it (seeking to the keyframe before the
    chunk) and keeps that chunk, so frames read forwards or backwards (a ping-pong through the
    clip) cost about one decode each, and at most ``chunk`` frames are held: a 1080p clip of any
    length is read in a few hundred megabytes.

    Args:
        path: The video file.
        chunk: Frames decoded and held together.

    Raises:
        MediaError: The file is missing or unreadable, has no video stream, or a frame does not
            decode.
    """

    def __init__(self, path: str | Path, chunk: int = 32) -> None:
        if chunk < 1:
            raise ValueError(f"chunk must be >= 1; got {chunk}")
        self.path = Path(path)
        self.times = frame_times(self.path)
        self.chunk = int(chunk)
        self._container = _open(self.path)
        self._stream = _video_stream(self.path, self._container)
        self._turns: int | None = None
        self._held: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.times)

    def __enter__(self) -> "FrameReader":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the file."""
        self._container.close()
        self._held = {}

    def __getitem__(self, index: int) -> np.ndarray:
        """Frame ``index`` (uint8 RGB ``(H, W, 3)``, upright)."""
        n = len(self.times)
        if not -n <= index < n:
            raise IndexError(f"{self.path}: frame {index} of {n}")
        index %= n
        if index not in self._held:
            self._load(index // self.chunk)
        return self._held[index]

    def _load(self, c: int) -> None:
        av = _av()
        lo, hi = c * self.chunk, min((c + 1) * self.chunk, len(self.times))
        self._held = {}
        stream = self._stream
        step = float(np.median(np.diff(self.times))) if len(self.times) > 1 else 1.0
        try:
            self._container.seek(int(np.floor(self.times[lo] / stream.time_base)), stream=stream, backward=True, any_frame=False)
            for frame in self._container.decode(stream):
                if frame.time is None:
                    continue
                k = int(np.searchsorted(self.times, float(frame.time) - 0.25 * step))
                if k < lo:
                    continue
                if k >= hi:
                    break
                if self._turns is None:
                    self._turns = _upright_turns(self.path, getattr(frame, "rotation", 0) or 0)
                rgb = frame.to_ndarray(format="rgb24")
                self._held[k] = np.ascontiguousarray(np.rot90(rgb, -self._turns)) if self._turns else rgb
        except av.error.FFmpegError as exc:
            raise MediaError(f"{self.path}: cannot decode frames {lo}-{hi - 1} ({exc.strerror or exc})") from exc
        missing = [k for k in range(lo, hi) if k not in self._held]
        if missing:
            raise MediaError(f"{self.path}: frames {missing[0]}-{missing[-1]} did not decode")


def _decode_audio(path: Path, container, sample_rate: int | None, *, partial: list[str] | None = None) -> AudioTrack:
    """The first audio stream, mono. With ``partial`` (a list), a stream that stops decoding part
    way gives the samples before the fault and appends a line saying where; without, it raises."""
    av = _av()
    stream = container.streams.audio[0]
    target_rate = int(sample_rate or stream.rate or 0)
    if target_rate <= 0:
        raise MediaError(f"{path}: audio stream has no sample rate")
    # Keep the channels through the resampler and average them here: FFmpeg's own mono downmix
    # scales each channel by 1/sqrt(2), which takes identical full-scale channels out of [-1, 1].
    resampler = av.AudioResampler(format="fltp", layout=stream.layout.name, rate=target_rate)
    chunks: list[np.ndarray] = []
    start: float | None = None
    try:
        for frame in container.decode(stream):
            if start is None:
                start = float(frame.time) if frame.time is not None else 0.0
            for out in resampler.resample(frame):
                chunks.append(out.to_ndarray().mean(axis=0))
        for out in resampler.resample(None):
            chunks.append(out.to_ndarray().mean(axis=0))
    except av.error.FFmpegError as exc:
        if partial is None or not chunks:
            raise MediaError(f"{path}: cannot decode the audio stream ({exc.strerror or exc})") from exc
        partial.append(f"the audio stops decoding {sum(map(len, chunks)) / target_rate:.2f} s after its start ({exc.strerror or exc})")
    samples = np.concatenate(chunks).astype(np.float32) if chunks else np.zeros(0, np.float32)
    return AudioTrack(samples=samples, sample_rate=target_rate, start=start or 0.0)


def audio_span(track: AudioTrack, t0: float, t1: float | None) -> AudioTrack:
    """The part of ``track`` between container times ``t0`` and ``t1`` (``None``: to its end),
    keeping its clock (``start`` is when its first kept sample plays)."""
    rate = track.sample_rate
    a = max(0, int(round((t0 - track.start) * rate)))
    b = len(track.samples) if t1 is None else max(a, int(round((t1 - track.start) * rate)))
    return AudioTrack(track.samples[a:b], rate, track.start + a / rate)


def read_audio(path: str | Path, sample_rate: int | None = None) -> AudioTrack:
    """Decode the first audio stream of a file to mono float32.

    Args:
        path: Any file FFmpeg reads (wav, mp3, m4a, flac, mp4, ...).
        sample_rate: Resample to this rate; ``None`` keeps the native rate.

    Returns:
        An :class:`AudioTrack`.

    Raises:
        MediaError: The file is missing, unreadable, has no audio stream, or cannot be decoded.
    """
    p = Path(path)
    with _open(p) as container:
        if not container.streams.audio:
            raise MediaError(f"{p}: has no audio track")
        return _decode_audio(p, container, sample_rate)


def read_video(
    path: str | Path,
    *,
    audio: bool = True,
    audio_rate: int | None = None,
    max_frames: int | None = None,
    start: float = 0.0,
    end: float | None = None,
    transform: Callable[[np.ndarray], np.ndarray] | None = None,
    every: int = 1,
) -> Video:
    """Decode a video's frames with their timestamps, and optionally its audio.

    Variable frame rate input is handled: each frame carries its own presentation time. A file
    whose frames stop decoding before its declared end (cut off mid-write) gives the frames that
    decode, with ``Video.truncated`` saying where it ends.

    Args:
        path: The video file.
        audio: Also decode the audio track (``Video.audio`` is ``None`` when there is none).
        audio_rate: Resample the audio to this rate; ``None`` keeps the native rate.
        max_frames: Stop after this many frames.
        start: Seconds from the first frame's time: earlier frames are skipped (a trim).
        end: Seconds from the first frame's time: frames from then on are not decoded; the audio
            is cut to the same span (``start`` to ``end``), so frames and sound stay together.
        transform: Applied to each upright frame as it is decoded (a crop, a resize): the clip is
            held at the size it returns, never at the file's.
        every: Keep every ``every``-th frame from ``start`` on (a sample of the clip).

    Returns:
        A :class:`Video`.

    Raises:
        MediaError: The file is missing, unreadable, has no video stream, or no frame decodes.
        adnerf.memory.MemoryNeedError: The container's frame count says the decoded frames would
            not fit in the memory available (checked before decoding).
    """
    av = _av()
    p = Path(path)
    truncated = None
    turns = 0
    with _open(p) as container:
        stream = _video_stream(p, container)
        fps = float(stream.average_rate) if stream.average_rate else 0.0
        declared = int(stream.frames or 0)
        count = min(declared, max_frames or declared)
        if start < 0 or (end is not None and not end > start):
            raise MediaError(f"{p}: a trim needs 0 <= start < end; got start {start:g} s, end {end} s")
        if count and stream.codec_context.width and transform is None and not start and end is None and every == 1:  # the container's frame count, where it gives one
            require(count * stream.codec_context.width * stream.codec_context.height * 3, f"{p}: {count} frames of {stream.codec_context.width}x{stream.codec_context.height} (decoded RGB)")
        first_time: float | None = None
        kept = 0  # frames from start on
        frames: list[np.ndarray] = []
        times: list[float] = []

        def stopped(why: str) -> str:
            of = f" of the {declared} the file declares" if declared else ""
            return f"decoding stopped after frame {len(frames)}{of}, {max(times):.2f} s in{why}"

        try:
            for k, frame in enumerate(container.decode(stream)):
                time = float(frame.time) if frame.time is not None else k / (fps or 25.0)
                if first_time is None:
                    first_time = time
                    turns = _upright_turns(p, getattr(frame, "rotation", 0) or 0)
                if time - first_time < start - 1e-6:
                    continue
                if end is not None and time - first_time >= end - 1e-6:
                    break
                kept += 1
                if (kept - 1) % every:
                    continue
                rgb = frame.to_ndarray(format="rgb24")
                rgb = np.ascontiguousarray(np.rot90(rgb, -turns)) if turns else rgb  # rot90 turns counterclockwise
                frames.append(rgb if transform is None else np.ascontiguousarray(transform(rgb)))
                if len(frames) == 1 and (transform is not None or start or end is not None) and count:
                    held = count if end is None or not fps else min(count, int(np.ceil((end - start) * fps)) + 1)
                    require(held * frames[0].nbytes, f"{p}: up to {held} frames of {frames[0].shape[1]}x{frames[0].shape[0]} (decoded RGB)")
                times.append(time)
                if max_frames is not None and len(frames) >= max_frames:
                    break
        except av.error.FFmpegError as exc:
            if not frames:
                raise MediaError(f"{p}: cannot decode the video stream ({exc.strerror or exc})") from exc
            truncated = stopped(f" ({exc.strerror or exc})")
        if not frames and first_time is not None and start:
            raise MediaError(f"{p}: no frame {start:g} s or later after the first (the trim's start lies past the clip's end)")
        if not frames:
            raise MediaError(f"{p}: the video stream has no decodable frames")
        if truncated is None and max_frames is None and not start and end is None and every == 1 and declared > len(frames) + max(2, declared // 100):
            truncated = stopped("")
    track = None
    if audio:
        with _open(p) as container:
            if container.streams.audio:
                faults: list[str] = []
                track = _decode_audio(p, container, audio_rate, partial=faults)
                if (start or end is not None) and first_time is not None:
                    track = audio_span(track, first_time + start, None if end is None else first_time + end)
                if faults:
                    truncated = "; ".join(x for x in (truncated, *faults) if x)
    order = np.argsort(np.asarray(times), kind="stable")
    stacked = np.empty((len(frames), *frames[0].shape), frames[0].dtype)
    for k, i in enumerate(order):  # each decoded frame freed once copied: the clip is held once, not twice
        stacked[k], frames[i] = frames[i], None  # type: ignore[call-overload]
    return Video(
        frames=stacked,
        timestamps=np.asarray(times, dtype=np.float64)[order],
        fps=fps,
        audio=track,
        rotation=90 * turns,
        truncated=truncated,
    )


def read_rgb(path: str | Path) -> np.ndarray:
    """An image file as uint8 RGB ``(H, W, 3)``.

    Raises:
        MediaError: A missing or unreadable image.
    """
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise MediaError(f"{path}: missing or unreadable image")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_image(path: str | Path, height: int, width: int) -> np.ndarray:
    """An RGB image cropped to the aspect of ``(height, width)`` about its centre and resized (area
    resampling) to ``(height, width, 3)`` float32 in [0, 1].

    Raises:
        MediaError: A missing or unreadable image.
    """
    img = read_rgb(path).astype(np.float32) / 255.0
    h, w = img.shape[:2]
    target = width / height
    if w / h > target:
        cw = int(round(h * target))
        img = img[:, (w - cw) // 2 : (w - cw) // 2 + cw]
    else:
        ch = int(round(w / target))
        img = img[(h - ch) // 2 : (h - ch) // 2 + ch]
    return cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)


class VideoWriter:
    """An mp4 (h264 yuv420p + aac mono) written frame by frame: memory holds one frame, not the clip.

    Use as a context manager::

        with VideoWriter("out.mp4", 25.0, audio=track) as writer:
            for frame in frames:
                writer.write(frame)

    The audio is written when the block ends, with sample 0 at the time of frame 0. The file is
    written to a temporary sibling and renamed into place only when the block ends without an
    error, so a failure or an interrupt leaves nothing partial. Frames with odd width or height
    are padded by one replicated row / column (h264's 4:2:0 needs even sizes); every frame must
    have the first one's size.

    Args:
        path: Output ``.mp4`` path.
        fps: Frame rate (may be fractional, e.g. 29.97).
        audio: Mono samples ``(n,)`` (float in ``[-1, 1]``) or an :class:`AudioTrack`; ``None``
            writes a silent video.
        sample_rate: Rate of ``audio`` when it is an array.
        crf: h264 quality (lower is better; 18 is visually lossless).

    Raises:
        MediaError: Invalid frames or audio, or the encoder failed.
    """

    def __init__(self, path: str | Path, fps: float, audio: AudioTrack | np.ndarray | None = None, sample_rate: int | None = None, *, crf: int = 18) -> None:
        self.path = Path(path)
        if not fps or fps <= 0:
            raise MediaError(f"{self.path}: fps must be positive; got {fps}")
        if isinstance(audio, AudioTrack):
            sample_rate, audio = audio.sample_rate, audio.samples
        if audio is not None:
            audio = np.asarray(audio, dtype=np.float32).reshape(-1)
            if not sample_rate or sample_rate <= 0:
                raise MediaError(f"{self.path}: audio given without a positive sample_rate")
        self.audio, self.sample_rate, self.crf = audio, sample_rate, crf
        self.rate = Fraction(fps).limit_denominator(1001)
        self.frames_written = 0
        self._stack: ExitStack | None = None
        self._container = self._video = self._audio_stream = None
        self._size: tuple[int, int] | None = None

    def __enter__(self) -> "VideoWriter":
        stack = ExitStack()
        try:
            tmp = stack.enter_context(atomic_path(self.path))
            self._container = stack.enter_context(_av().open(str(tmp), "w", format="mp4"))
        except Exception as exc:
            stack.close()
            if isinstance(exc, OSError):
                raise
            raise MediaError(f"{self.path}: cannot create the video ({exc})") from exc
        self._stack = stack
        return self

    def append_audio(self, samples: np.ndarray) -> None:
        """Add mono samples to the end of the audio (a stream's sound, as it arrives; sample 0 still
        plays with frame 0). The writer must have been made with audio (an empty array will do)."""
        if self.audio is None:
            raise MediaError(f"{self.path}: append_audio on a writer made without audio (give audio=np.zeros(0) and a sample_rate)")
        self.audio = np.concatenate([self.audio, np.asarray(samples, dtype=np.float32).reshape(-1)])

    def write(self, frame: np.ndarray) -> None:
        """Encode one uint8 RGB frame ``(H, W, 3)`` (or float in ``[0, 1]``, converted)."""
        if self._container is None:
            raise MediaError(f"{self.path}: write() outside the writer's with-block")
        img = np.asarray(frame)
        if img.ndim != 3 or img.shape[-1] != 3 or img.shape[0] == 0 or img.shape[1] == 0:
            raise MediaError(f"{self.path}: a frame must have shape (H, W, 3); got {img.shape}")
        if img.dtype != np.uint8:
            img = (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        if img.shape[0] % 2 or img.shape[1] % 2:
            img = np.pad(img, ((0, img.shape[0] % 2), (0, img.shape[1] % 2), (0, 0)), mode="edge")
        try:
            if self._video is None:
                self._size = img.shape[:2]
                self._video = self._container.add_stream("libx264", rate=self.rate)
                self._video.width, self._video.height = img.shape[1], img.shape[0]
                self._video.pix_fmt = "yuv420p"
                self._video.options = {"crf": str(self.crf)}
                if self.audio is not None:  # every stream is added before the first frame is muxed
                    self._audio_stream = self._container.add_stream("aac", rate=int(self.sample_rate))
                    self._audio_stream.layout = "mono"
            elif img.shape[:2] != self._size:
                raise MediaError(f"{self.path}: frame {self.frames_written} is {img.shape[1]}x{img.shape[0]}, the first was {self._size[1]}x{self._size[0]}")
            vf = _av().VideoFrame.from_ndarray(np.ascontiguousarray(img), format="rgb24")
            vf.pts = self.frames_written
            vf.time_base = Fraction(1, 1) / self.rate
            self._container.mux(self._video.encode(vf))
        except MediaError:
            raise
        except Exception as exc:
            raise MediaError(f"{self.path}: writing the video failed ({exc})") from exc
        self.frames_written += 1

    def _finish(self) -> None:
        if self._video is None:
            raise MediaError(f"{self.path}: no frames were written")
        try:
            self._container.mux(self._video.encode())
            if self._audio_stream is not None:
                block = 1024
                for s in range(0, len(self.audio), block):
                    af = _av().AudioFrame.from_ndarray(np.ascontiguousarray(self.audio[None, s : s + block]), format="flt", layout="mono")
                    af.sample_rate = int(self.sample_rate)
                    af.pts = s
                    af.time_base = Fraction(1, int(self.sample_rate))
                    self._container.mux(self._audio_stream.encode(af))
                self._container.mux(self._audio_stream.encode())
        except Exception as exc:
            raise MediaError(f"{self.path}: writing the video failed ({exc})") from exc

    def __exit__(self, kind, exc, tb) -> bool:  # noqa: ANN001
        stack, self._stack = self._stack, None
        try:
            if kind is None:
                self._finish()
        except BaseException:
            stack.__exit__(*sys.exc_info())  # the container closed, the temporary file removed
            raise
        finally:
            self._container = self._video = self._audio_stream = None
        stack.__exit__(kind, exc, tb)  # on success: the trailer written, the file renamed into place
        return False


def write_video(
    path: str | Path,
    frames: np.ndarray,
    fps: float,
    audio: AudioTrack | np.ndarray | None = None,
    sample_rate: int | None = None,
    *,
    crf: int = 18,
) -> Path:
    """Encode an mp4 (h264 yuv420p + aac mono) with audio aligned to the first frame.

    The frames are handed to a :class:`VideoWriter` one by one (which see for ``path``, ``fps``,
    ``audio``, ``sample_rate`` and ``crf``: odd sizes are padded, the file appears only when
    complete).

    Args:
        frames: uint8 RGB frames ``(N, H, W, 3)`` (or float in ``[0, 1]``, converted).

    Returns:
        The written path.

    Raises:
        MediaError: Invalid frames or audio, or the encoder failed.
    """
    out = Path(path)
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.shape[0] == 0:
        raise MediaError(f"{out}: frames must have shape (N, H, W, 3) with N >= 1; got {frames.shape}")
    with VideoWriter(out, fps, audio, sample_rate, crf=crf) as writer:
        for img in frames:
            writer.write(img)
    return out
