//! The NC side, as pure code: what a control is told and in which words. A measurement plan
//! becomes a program in one control's dialect (`program`), a program is read back into the
//! moves it commands (`reader`), and compensation values become that control's variables and
//! the program text that writes them (`offsets`); a lathe facing pass through given points
//! (`facing`: a correction table as a program). No I/O: text in, text out.

mod blocks;
pub mod dialect;
pub mod facing;
pub mod offsets;
pub mod program;
pub mod reader;
