"""Speech with known phoneme timings: espeak-ng's library through ``ctypes``.

The ``espeak-ng`` program prints phonemes but not *when* they are spoken (its ``--pho`` output
needs mbrola voices). The library reports them itself: initialised with phoneme events and IPA
names, in synchronous mode, it hands each block of synthesised samples to a callback together
with the events of that block, and each phoneme event carries its position in the audio in
milliseconds. :func:`speak` collects both, so a sentence comes back as samples plus a list of
``(start time, IPA name)`` — the timing truth the viseme-driven synthetic scene is built on.

The library keeps global state (one voice, one rate, one callback per process, and a wave
generator whose output depends on what it spoke before), so :func:`speak` runs it in a fresh
child process per call: the same request always gives the same samples and timings, and calls
from several threads do not mix.
Only ``libespeak-ng.so.1`` (Debian / Ubuntu ``espeak-ng`` or ``libespeak-ng1``) is needed, not
its headers. Where it is missing, :func:`espeak_library` raises :class:`EspeakError` with the fix.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["PAUSE", "EspeakError", "Phoneme", "Utterance", "check_voice", "espeak_library", "espeak_ready", "speak"]

# espeak_ng's speak_lib.h (stable API since espeak 1.48).
_AUDIO_OUTPUT_SYNCHRONOUS = 2
_INITIALIZE_PHONEME_EVENTS = 0x0001
_INITIALIZE_PHONEME_IPA = 0x0002
_INITIALIZE_DONT_EXIT = 0x8000
_EVENT_LIST_TERMINATED = 0
_EVENT_PHONEME = 7
_EVENT_SAMPLERATE = 8
_POS_CHARACTER = 1
_CHARS_UTF8 = 1
_PARAM_RATE = 1
_PARAM_PITCH = 3
_EE_OK = 0

PAUSE = "_"  # the name of a pause in :attr:`Utterance.phonemes`


class _EventId(ctypes.Union):
    _fields_ = [("number", ctypes.c_int), ("name", ctypes.c_char_p), ("string", ctypes.c_char * 8)]


class _Event(ctypes.Structure):
    _fields_ = [
        ("type", ctypes.c_int),
        ("unique_identifier", ctypes.c_uint),
        ("text_position", ctypes.c_int),
        ("length", ctypes.c_int),
        ("audio_position", ctypes.c_int),  # milliseconds from the start of the utterance
        ("sample", ctypes.c_int),
        ("user_data", ctypes.c_void_p),
        ("id", _EventId),
    ]


_Callback = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(ctypes.c_short), ctypes.c_int, ctypes.POINTER(_Event))


class EspeakError(RuntimeError):
    """espeak-ng's library is missing or refused a request; the message says what to do."""


@dataclass(frozen=True)
class Phoneme:
    """One phoneme as espeak-ng spoke it.

    Attributes:
        start: Seconds from the utterance's first sample to the phoneme's start.
        ipa: The phoneme's IPA name (may carry length or stress marks, e.g. ``"aɪ"``, ``"iː"``),
            or :data:`PAUSE` for a pause.
    """

    start: float
    ipa: str


@dataclass(frozen=True)
class Utterance:
    """Synthesised speech and when each phoneme starts in it.

    Attributes:
        samples: ``(n,)`` float32 mono samples in [-1, 1].
        sample_rate: Samples per second (espeak-ng speaks at 22050 Hz).
        phonemes: The phonemes in order of their start times. A phoneme ends where the next one
            starts; the last ends at the end of ``samples``.
    """

    samples: np.ndarray
    sample_rate: int
    phonemes: tuple[Phoneme, ...]

    @property
    def duration(self) -> float:
        """Seconds of audio."""
        return len(self.samples) / self.sample_rate


_LIB: ctypes.CDLL | None = None
_RATE = 0
_STATE: dict[str, object] = {}

# espeak-ng's output depends on what the process spoke before (its wave generator keeps state
# between utterances: the same sentence comes out a few samples longer or shorter), while its
# first utterances in a fresh process are the same every time. So each request runs in a fresh
# child process: the same text, voice and rate always give the same samples and timings.
_CHILD = (
    "import importlib.util, sys; "
    "spec = importlib.util.spec_from_file_location('_adnerf_espeak_child', sys.argv[1]); "
    "module = importlib.util.module_from_spec(spec); sys.modules[spec.name] = module; "
    "spec.loader.exec_module(module); module._child_main()"
)


def _load() -> ctypes.CDLL:
    """The library with its functions' signatures, not initialised."""
    name = ctypes.util.find_library("espeak-ng") or "libespeak-ng.so.1"
    try:
        lib = ctypes.CDLL(name)
    except OSError as exc:
        raise EspeakError("espeak-ng's library is not installed (apt install espeak-ng, or brew install espeak-ng)") from exc
    lib.espeak_Initialize.restype = ctypes.c_int
    lib.espeak_Initialize.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_char_p, ctypes.c_int]
    lib.espeak_SetSynthCallback.restype = None
    lib.espeak_SetSynthCallback.argtypes = [_Callback]
    lib.espeak_SetVoiceByName.restype = ctypes.c_int
    lib.espeak_SetVoiceByName.argtypes = [ctypes.c_char_p]
    lib.espeak_SetParameter.restype = ctypes.c_int
    lib.espeak_SetParameter.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int]
    lib.espeak_Synth.restype = ctypes.c_int
    lib.espeak_Synth.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_uint, ctypes.c_int, ctypes.c_uint, ctypes.c_uint, ctypes.c_void_p, ctypes.c_void_p]
    return lib


def espeak_library() -> tuple[ctypes.CDLL, int]:
    """The library initialised in this process, and its sample rate (once per process).

    :func:`speak` calls it in a child process; calling it here makes this process's later
    utterances depend on each other (see the module's notes).

    Raises:
        EspeakError: ``libespeak-ng.so.1`` is not installed or does not initialise.
    """
    global _LIB, _RATE
    if _LIB is not None:
        return _LIB, _RATE
    lib = _load()
    rate = lib.espeak_Initialize(_AUDIO_OUTPUT_SYNCHRONOUS, 0, None, _INITIALIZE_PHONEME_EVENTS | _INITIALIZE_PHONEME_IPA | _INITIALIZE_DONT_EXIT)
    if rate <= 0:
        raise EspeakError(f"espeak-ng's library did not initialise (code {rate}); is espeak-ng-data installed?")

    def on_synth(wav, count, events) -> int:  # collects into _STATE; 0 = go on
        if count > 0 and wav:
            _STATE["chunks"].append(np.ctypeslib.as_array(wav, shape=(count,)).copy())  # type: ignore[union-attr]
        k = 0
        while events[k].type != _EVENT_LIST_TERMINATED:
            event = events[k]
            if event.type == _EVENT_PHONEME:
                raw = bytes(event.id.string).split(b"\0", 1)[0]
                _STATE["events"].append((event.audio_position, raw.decode("utf-8", "replace")))  # type: ignore[union-attr]
            k += 1
        return 0

    callback = _Callback(on_synth)
    lib.espeak_SetSynthCallback(callback)
    _STATE["callback"] = callback  # keep the C function pointer alive
    _LIB, _RATE = lib, rate
    return lib, rate


def _speak_here(text: str, voice: str, words_per_minute: int, pitch: int) -> tuple[int, np.ndarray, list[tuple[int, str]]]:
    """Synthesise in this process: sample rate, int16 samples, ``(ms, name)`` phoneme events."""
    lib, rate = espeak_library()
    if lib.espeak_SetVoiceByName(voice.encode("utf-8")) != _EE_OK:
        raise EspeakError(f"espeak-ng has no voice {voice!r} (espeak-ng --voices lists them)")
    if not text:
        return rate, np.zeros(0, np.int16), []
    lib.espeak_SetParameter(_PARAM_RATE, int(words_per_minute), 0)
    lib.espeak_SetParameter(_PARAM_PITCH, int(pitch), 0)
    _STATE["chunks"], _STATE["events"] = [], []
    data = text.encode("utf-8") + b"\0"
    buffer = ctypes.create_string_buffer(data)
    code = lib.espeak_Synth(buffer, len(data), 0, _POS_CHARACTER, 0, _CHARS_UTF8, None, None)
    if code != _EE_OK:
        raise EspeakError(f"espeak-ng could not speak the text (code {code})")
    chunks: list = _STATE["chunks"]  # type: ignore[assignment]
    pcm = np.concatenate(chunks).astype(np.int16) if chunks else np.zeros(0, np.int16)
    return rate, pcm, list(_STATE["events"])  # type: ignore[call-overload]


def _child_main() -> None:
    """Child side of :func:`_in_child`: a JSON request on stdin; a JSON header line and the raw
    int16 samples on stdout, or the error on stderr with exit status 3."""
    request = json.loads(sys.stdin.read())
    try:
        rate, pcm, events = _speak_here(request["text"], request["voice"], request["words_per_minute"], request["pitch"])
    except EspeakError as exc:
        sys.stderr.write(str(exc))
        sys.exit(3)
    header = json.dumps({"rate": rate, "events": events, "samples": int(pcm.size)}).encode() + b"\n"
    sys.stdout.buffer.write(header + pcm.astype("<i2").tobytes())


def _in_child(text: str, voice: str, words_per_minute: int, pitch: int) -> tuple[int, np.ndarray, list[tuple[int, str]]]:
    request = json.dumps({"text": text, "voice": voice, "words_per_minute": words_per_minute, "pitch": pitch})
    done = subprocess.run([sys.executable, "-I", "-c", _CHILD, str(Path(__file__).resolve())], input=request.encode(), capture_output=True, check=False)
    if done.returncode == 3:
        raise EspeakError(done.stderr.decode("utf-8", "replace").strip())
    if done.returncode != 0:
        raise EspeakError(f"espeak-ng's process failed (exit {done.returncode}): {done.stderr.decode('utf-8', 'replace').strip()[-500:]}")
    line, _, raw = done.stdout.partition(b"\n")
    header = json.loads(line)
    pcm = np.frombuffer(raw, dtype="<i2").astype(np.int16)
    if pcm.size != header["samples"]:
        raise EspeakError(f"espeak-ng's process returned {pcm.size} of {header['samples']} samples")
    return int(header["rate"]), pcm, [(int(ms), str(name)) for ms, name in header["events"]]


def espeak_ready() -> bool:
    """Whether espeak-ng's library is installed here (what :func:`speak` needs)."""
    try:
        _load()
    except EspeakError:
        return False
    return True


def check_voice(voice: str) -> None:
    """Raise :class:`EspeakError` unless espeak-ng is here and knows ``voice``."""
    _load()
    _in_child("", voice, 150, 50)


def speak(text: str, voice: str = "en", words_per_minute: int = 150, pitch: int = 50) -> Utterance:
    """Speak ``text`` with espeak-ng and report when each phoneme starts.

    Deterministic: the same arguments give the same samples and timings, whatever was spoken
    before (each call synthesises in a fresh child process, about 0.1 s of overhead).

    Args:
        text: What to say (UTF-8).
        voice: An espeak-ng voice name, optionally with a variant: ``"en"``, ``"en-us"``,
            ``"en+f3"`` (a female variant), ``"de"`` ... (``espeak-ng --voices`` lists them).
        words_per_minute: Speaking rate, 80 to 450.
        pitch: Base pitch, 0 to 100 (50 is the voice's own).

    Returns:
        The samples at espeak-ng's rate (22050 Hz) and the phonemes with their start times.

    Raises:
        EspeakError: The library is missing, or the voice is unknown.
        ValueError: Empty text, or a rate or pitch out of range.
    """
    if not text.strip():
        raise ValueError("nothing to say: the text is empty")
    if not 80 <= words_per_minute <= 450:
        raise ValueError(f"words_per_minute must lie in [80, 450]; got {words_per_minute}")
    if not 0 <= pitch <= 100:
        raise ValueError(f"pitch must lie in [0, 100]; got {pitch}")
    _load()
    rate, pcm, events = _in_child(text, voice, int(words_per_minute), int(pitch))
    samples = (pcm.astype(np.float32) / 32768.0).astype(np.float32)
    # espeak-ng reports pauses as phonemes without a name; they are named PAUSE here.
    phonemes = tuple(Phoneme(ms / 1000.0, ipa.strip() or PAUSE) for ms, ipa in sorted(events, key=lambda e: e[0]))
    return Utterance(samples, rate, phonemes)
