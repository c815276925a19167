//! Files written front to back whose pages are sent to disk while the rest is still being produced.
//!
//! Linux starts writing dirty pages on its own only past its thresholds (a share of memory, or an age of 30 s), so
//! the final `fsync` of a file written faster than that may have to write gigabytes while the caller waits. Starting
//! each range's write-back as soon as it is complete lets the disk work beside the encoder, and the final sync finds
//! little left to do.

use std::fs::File;
use std::io::Write;

/// Bytes written after which their write-back to disk is started.
pub const WRITEBACK_BYTES: u64 = 32 << 20;

/// Asks the kernel to start writing `len` bytes of `file` from `offset` to disk without waiting for it (Linux);
/// elsewhere the final sync does all the work.
pub fn start_writeback(file: &File, offset: u64, len: u64) {
    #[cfg(target_os = "linux")]
    {
        use std::os::fd::AsRawFd;
        // SAFETY: a plain syscall on an open descriptor; a failure only means the final sync does more work.
        unsafe {
            libc::sync_file_range(file.as_raw_fd(), offset as i64, len as i64, libc::SYNC_FILE_RANGE_WRITE);
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = (file, offset, len);
}

/// A file written sequentially from its start that starts each [`WRITEBACK_BYTES`] on its way to disk once written.
/// Durability is unchanged: the caller still syncs the file when it is complete.
pub struct WritebackFile {
    file: File,
    written: u64,
    flushed: u64,
}

impl WritebackFile {
    pub fn new(file: File) -> WritebackFile {
        WritebackFile::resuming(file, 0)
    }

    /// A file whose first `offset` bytes are already written (and left to the final sync); writes continue there.
    pub fn resuming(file: File, offset: u64) -> WritebackFile {
        WritebackFile {
            file,
            written: offset,
            flushed: offset,
        }
    }

    /// Bytes in the file: those it was resumed from and those written since.
    pub fn bytes_written(&self) -> u64 {
        self.written
    }

    pub fn into_inner(self) -> File {
        self.file
    }
}

impl Write for WritebackFile {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.file.write(buf)?;
        self.written += n as u64;
        if self.written - self.flushed >= WRITEBACK_BYTES {
            start_writeback(&self.file, self.flushed, self.written - self.flushed);
            self.flushed = self.written;
        }
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.file.flush()
    }
}

#[cfg(test)]
mod tests {
    use std::io::Read;

    use super::*;

    #[test]
    fn what_is_written_is_the_file_whatever_the_write_back() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f");
        let mut w = WritebackFile::new(File::create(&path).unwrap());
        let block: Vec<u8> = (0..(5 << 20)).map(|i: u32| (i % 251) as u8).collect();
        for _ in 0..8 {
            w.write_all(&block).unwrap();
        }
        assert!(
            w.flushed >= WRITEBACK_BYTES,
            "write-back started after {} bytes",
            w.flushed
        );
        w.into_inner().sync_all().unwrap();
        let mut back = Vec::new();
        File::open(&path).unwrap().read_to_end(&mut back).unwrap();
        assert_eq!(back.len(), 8 * block.len());
        assert!(back.chunks(block.len()).all(|c| c == block.as_slice()));
    }
}
