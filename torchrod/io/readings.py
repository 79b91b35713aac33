"""FBG readings, one import away: the names of the modules that read them, gathered.

``from torchrod.io.readings import ...`` gives each of these; they live in the modules that hold one thing each:

* :mod:`torchrod.io.reading`: the record (:class:`~torchrod.io.reading.Reading`), its checks (ids, time stamps,
  grating positions), :func:`~torchrod.io.reading.parse_reading`, :func:`~torchrod.io.reading.to_reading` and
  :func:`~torchrod.io.reading.stack_readings`;
* :mod:`torchrod.io.quantities`: what a reading gives per grating (:data:`~torchrod.io.quantities.QUANTITIES`:
  curvature, core strains, polar curvature, peak wavelengths or shifts) and its conversion to curvature [1/m];
* :mod:`torchrod.io.numbers`: numbers of a decoded reading and of a CSV cell;
* :mod:`torchrod.io.values`: how a message quotes a value, and the stand-in for an integer too long to convert;
* :mod:`torchrod.io.csv_rows`: CSV rows and their header (:class:`~torchrod.io.csv_rows.CsvLayout`);
* :mod:`torchrod.io.sources`: a file, standard input or a TCP connection read line by line
  (:class:`~torchrod.io.sources.ReadingSource`, :func:`~torchrod.io.sources.iter_readings`), each line in the
  format its name or content says.
"""

from __future__ import annotations

from .csv_rows import CsvLayout, csv_id, parse_csv_row
from .numbers import as_number, csv_number
from .quantities import (
    MAX_CURVATURE,
    QUANTITIES,
    curvature_tensor,
    polar_curvature,
    reading_curvature,
    strain_curvature,
    wavelength_curvature,
    wavelength_shifts,
    wavelength_values,
)
from .reading import (
    MAX_ID_CHARS,
    MAX_ID_DEPTH,
    Reading,
    check_gratings,
    check_id,
    check_time,
    id_problem,
    parse_reading,
    stack_readings,
    to_reading,
)
from .sources import (
    FORMATS,
    LINE_BYTES_PER_VALUE,
    MIN_LINE_BYTES,
    ReadingSource,
    detect_format,
    iter_readings,
    iter_records,
    line_limit,
    unusable_lines,
)
from .values import MAX_INT_DIGITS, QUOTE_CHARS, HugeInteger, describe, quote

__all__ = [
    "FORMATS",
    "LINE_BYTES_PER_VALUE",
    "MAX_CURVATURE",
    "MAX_ID_CHARS",
    "MAX_ID_DEPTH",
    "MAX_INT_DIGITS",
    "MIN_LINE_BYTES",
    "QUANTITIES",
    "QUOTE_CHARS",
    "CsvLayout",
    "HugeInteger",
    "Reading",
    "ReadingSource",
    "as_number",
    "check_gratings",
    "check_id",
    "check_time",
    "csv_id",
    "csv_number",
    "curvature_tensor",
    "describe",
    "detect_format",
    "id_problem",
    "iter_readings",
    "iter_records",
    "line_limit",
    "parse_csv_row",
    "parse_reading",
    "polar_curvature",
    "quote",
    "reading_curvature",
    "stack_readings",
    "strain_curvature",
    "to_reading",
    "unusable_lines",
    "wavelength_curvature",
    "wavelength_shifts",
    "wavelength_values",
]
