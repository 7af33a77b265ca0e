//! Reads numpy `.npz` archives and `.npy` files into an [`UploadSource`], streaming the data.
//!
//! Trajectories ([`trajectories_from_npz`]) follow the rules every reader shares
//! ([`crate::values`], [`crate::episodes`], `docs/data-formats.md`): observations and actions of
//! any integer or float dtype in either byte order are sent as float32 rows, converted as they
//! are read; episode flags of bool or of numbers that are all 0 or 1 are sent as bool.
//! Samples ([`samples_from_npz_or_npy`]) are sent as stored, so only little-endian (or
//! byte-order-free) `float32` and `float64` are taken there. Everything else (Fortran order,
//! object/pickled arrays, strings, complex numbers) is refused with an error that names the
//! array and its dtype string, so the fix (`astype`, `np.ascontiguousarray`) is obvious.
//!
//! Opening a file reads only the npy headers of the arrays that will be sent; [`NpzSource::open`]
//! reopens an array and returns a reader of exactly its declared data bytes, so files larger
//! than memory upload fine.
//!
//! Malformed input is an error, never a panic: the header text is checked (ASCII, bounded
//! size and nesting, plain decimal dimensions whose product fits in 64 bits) before `npyz`
//! parses it, and declared sizes are checked against the file before any data is read.
//!
//! Entry points:
//! - [`trajectories_from_npz`]: D4RL / Minari style `observations`, `actions` and episode
//!   boundaries (flags, start indices or lengths: [`crate::episodes`]).
//! - [`walls_from_npz`]: maze walls from `walls` / `wall_map` / `maze_map` in the file.
//! - [`samples_from_npz_or_npy`]: one `[N, ...]` float array, sent as `samples`.
//! - [`detect_kind`]: which of the two a file looks like.
//! - [`read_npy_header`]: the checked header parser on its own (useful for fuzzing).
//! - [`NpzSource::read_tensor`]: one array whole in memory (inputs of `score` and `grad`).
//! - [`npz_keys`], [`read_numbers`], [`npz_array_shape`]: one archive's names, one array as
//!   numbers or its shape, without making an upload.
//!
//! Module map, from the dataset down to the bytes:
//! - `trajectories`: which arrays make a trajectory dataset and under which names they are
//!   sent; [`detect_kind`]; the maze walls of a file.
//! - `samples`: the one float array of a samples dataset.
//! - `source`: [`NpzSource`], the chosen arrays as an [`UploadSource`] (reopened and checked
//!   when sent).
//! - `stream`: readers over one array's data: exactly its declared bytes, or converted to
//!   float32 as read.
//! - `archive`: `.npy` or `.npz`, the archive's members, one member's header or values.
//! - `npy`: one `.npy` array's header (checked, parsed, and written: [`crate::npz_write`] uses
//!   the same writer), its dtype judged and its data decoded.
//! - `error`: [`NpzError`] and the pieces of messages.
//!
//! [`UploadSource`]: relreward_proto::upload::UploadSource

mod archive;
mod error;
mod npy;
mod samples;
mod source;
mod stream;
#[cfg(test)]
mod test_files;
mod trajectories;

pub use archive::{npz_array_shape, npz_keys, read_numbers};
pub use error::{NpzError, Result};
pub(crate) use npy::write_npy_header;
pub use npy::{MAX_HEADER_TEXT_BYTES, NpyInfo, read_npy_header};
pub use samples::samples_from_npz_or_npy;
pub use source::NpzSource;
pub use trajectories::{detect_kind, trajectories_from_npz, walls_from_npz};
