//! The only `unsafe` code in cubecal: memory-mapped V4L2 buffer queues driven by raw ioctls.
//!
//! Why not `v4l::io::mmap::Stream`: after a poll timeout its next `next()` re-queues a buffer that is
//! already queued (EINVAL), so a timed-out grab poisons the stream; it cannot dequeue without
//! re-queueing (needed by `flush`); its `Drop` panics when STREAMOFF fails with anything but ENODEV; and
//! its output side dequeues without polling on the O_NONBLOCK fd. This queue owns its mappings, tracks
//! which buffers are queued, waits with `poll()` and a deadline, and never panics.
#![allow(unsafe_code)]

use std::io;
use std::sync::Arc;
use std::time::Duration;

use v4l::device::Handle;
use v4l::v4l_sys;
use v4l::v4l2::{self, vidioc};

const POLLIN: i16 = 0x1;
const POLLOUT: i16 = 0x4;
const PROT_READ: i32 = 0x1;
const PROT_WRITE: i32 = 0x2;
const MAP_SHARED: i32 = 0x1;
/// `V4L2_BUF_FLAG_ERROR`: the driver says the buffer data may be corrupt.
pub(crate) const BUF_FLAG_ERROR: u32 = 0x40;

/// Direction of a queue.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Direction {
    Capture,
    Output,
}

/// A dequeued buffer's metadata.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Dequeued {
    pub index: usize,
    pub bytesused: usize,
    pub sequence: u32,
    pub timestamp: Duration,
    pub flags: u32,
}

struct Mapping {
    ptr: *mut u8,
    len: usize,
}

/// REQBUFS + QUERYBUF + mmap'ed buffers of one queue, with explicit queue/dequeue/wait.
pub(crate) struct MmapQueue {
    handle: Arc<Handle>,
    dir: Direction,
    maps: Vec<Mapping>,
    queued: Vec<bool>,
    streaming: bool,
}

// SAFETY: the mappings are owned exclusively by this value (never shared or aliased outside it) and are
// only accessed through `&self`/`&mut self`; the fd is a plain integer inside an `Arc<Handle>`.
unsafe impl Send for MmapQueue {}

impl std::fmt::Debug for MmapQueue {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MmapQueue")
            .field("fd", &self.handle.fd())
            .field("dir", &self.dir)
            .field("buffers", &self.maps.len())
            .field("streaming", &self.streaming)
            .finish()
    }
}

impl MmapQueue {
    fn buf_type(&self) -> u32 {
        buf_type(self.dir)
    }

    /// Request `count` buffers and map them. The driver may grant a different number (at least one).
    pub(crate) fn new(handle: Arc<Handle>, dir: Direction, count: u32) -> io::Result<MmapQueue> {
        let mut q = MmapQueue {
            handle,
            dir,
            maps: Vec::new(),
            queued: Vec::new(),
            streaming: false,
        };
        // SAFETY: plain-old-data structs zero-initialised as the V4L2 API expects; the pointers passed
        // to ioctl point at live locals of the type the request code expects.
        unsafe {
            let mut req: v4l_sys::v4l2_requestbuffers = std::mem::zeroed();
            req.count = count;
            req.type_ = q.buf_type();
            req.memory = v4l_sys::v4l2_memory_V4L2_MEMORY_MMAP;
            v4l2::ioctl(
                q.handle.fd(),
                vidioc::VIDIOC_REQBUFS,
                &mut req as *mut _ as *mut _,
            )?;
            if req.count == 0 {
                return Err(io::Error::new(
                    io::ErrorKind::OutOfMemory,
                    "driver granted no buffers",
                ));
            }
            for index in 0..req.count {
                let mut b: v4l_sys::v4l2_buffer = std::mem::zeroed();
                b.index = index;
                b.type_ = q.buf_type();
                b.memory = v4l_sys::v4l2_memory_V4L2_MEMORY_MMAP;
                v4l2::ioctl(
                    q.handle.fd(),
                    vidioc::VIDIOC_QUERYBUF,
                    &mut b as *mut _ as *mut _,
                )?;
                let len = b.length as usize;
                let ptr = v4l2::mmap(
                    std::ptr::null_mut(),
                    len,
                    PROT_READ | PROT_WRITE,
                    MAP_SHARED,
                    q.handle.fd(),
                    b.m.offset as _,
                )?;
                // pushed immediately so that Drop unmaps it even if a later buffer fails
                q.maps.push(Mapping {
                    ptr: ptr as *mut u8,
                    len,
                });
                q.queued.push(false);
            }
        }
        Ok(q)
    }

    pub(crate) fn len(&self) -> usize {
        self.maps.len()
    }

    pub(crate) fn is_streaming(&self) -> bool {
        self.streaming
    }

    pub(crate) fn is_queued(&self, index: usize) -> bool {
        self.queued.get(index).copied().unwrap_or(false)
    }

    /// The mapped bytes of buffer `index` (the whole buffer; use `bytesused` to cut it).
    pub(crate) fn buffer(&self, index: usize) -> &[u8] {
        match self.maps.get(index) {
            // SAFETY: the mapping is live until Drop, `len` is its length, and `&self` prevents a
            // concurrent `buffer_mut`. The driver writes only to buffers that are queued.
            Some(m) => unsafe { std::slice::from_raw_parts(m.ptr, m.len) },
            None => &[],
        }
    }

    /// Writable bytes of buffer `index` (for output queues; only while not queued).
    pub(crate) fn buffer_mut(&mut self, index: usize) -> &mut [u8] {
        match self.maps.get(index) {
            // SAFETY: as in `buffer`, and `&mut self` makes this the only reference.
            Some(m) => unsafe { std::slice::from_raw_parts_mut(m.ptr, m.len) },
            None => &mut [],
        }
    }

    /// Give buffer `index` to the driver (`bytesused` matters for output queues only).
    pub(crate) fn queue(&mut self, index: usize, bytesused: u32) -> io::Result<()> {
        if index >= self.maps.len() || self.queued[index] {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("buffer {index} is not dequeued"),
            ));
        }
        // SAFETY: zeroed POD struct passed to the matching ioctl.
        unsafe {
            let mut b: v4l_sys::v4l2_buffer = std::mem::zeroed();
            b.index = index as u32;
            b.type_ = self.buf_type();
            b.memory = v4l_sys::v4l2_memory_V4L2_MEMORY_MMAP;
            if self.dir == Direction::Output {
                b.bytesused = bytesused;
                b.field = v4l_sys::v4l2_field_V4L2_FIELD_NONE;
            }
            v4l2::ioctl(
                self.handle.fd(),
                vidioc::VIDIOC_QBUF,
                &mut b as *mut _ as *mut _,
            )?;
        }
        self.queued[index] = true;
        Ok(())
    }

    pub(crate) fn stream_on(&mut self) -> io::Result<()> {
        let mut t = self.buf_type();
        // SAFETY: STREAMON takes a pointer to the buffer type.
        unsafe {
            v4l2::ioctl(
                self.handle.fd(),
                vidioc::VIDIOC_STREAMON,
                &mut t as *mut _ as *mut _,
            )?;
        }
        self.streaming = true;
        Ok(())
    }

    /// STREAMOFF: the driver returns every buffer to us.
    pub(crate) fn stream_off(&mut self) -> io::Result<()> {
        let mut t = self.buf_type();
        // SAFETY: STREAMOFF takes a pointer to the buffer type.
        unsafe {
            v4l2::ioctl(
                self.handle.fd(),
                vidioc::VIDIOC_STREAMOFF,
                &mut t as *mut _ as *mut _,
            )?;
        }
        self.streaming = false;
        self.queued.iter_mut().for_each(|q| *q = false);
        Ok(())
    }

    /// Wait until a buffer can be dequeued, at most `timeout`. `Ok(false)` on timeout.
    pub(crate) fn wait(&self, timeout: Duration) -> io::Result<bool> {
        let events = match self.dir {
            Direction::Capture => POLLIN,
            Direction::Output => POLLOUT,
        };
        // round up so that a 0.5 ms remainder does not become a busy non-blocking poll loop
        let ms = timeout.as_micros().div_ceil(1000).min(i32::MAX as u128) as i32;
        match self.handle.poll(events, ms) {
            Ok(n) => Ok(n > 0),
            Err(e) if e.kind() == io::ErrorKind::Interrupted => Ok(false),
            Err(e) => Err(e),
        }
    }

    /// DQBUF without blocking (the fd is O_NONBLOCK). `Ok(None)` when nothing is ready (EAGAIN).
    pub(crate) fn dequeue(&mut self) -> io::Result<Option<Dequeued>> {
        // SAFETY: zeroed POD struct passed to the matching ioctl.
        let b = unsafe {
            let mut b: v4l_sys::v4l2_buffer = std::mem::zeroed();
            b.type_ = self.buf_type();
            b.memory = v4l_sys::v4l2_memory_V4L2_MEMORY_MMAP;
            match v4l2::ioctl(
                self.handle.fd(),
                vidioc::VIDIOC_DQBUF,
                &mut b as *mut _ as *mut _,
            ) {
                Ok(()) => b,
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => return Ok(None),
                Err(e) => return Err(e),
            }
        };
        let index = b.index as usize;
        if index >= self.maps.len() {
            return Err(io::Error::new(
                io::ErrorKind::InvalidData,
                format!(
                    "driver returned buffer index {index} of {}",
                    self.maps.len()
                ),
            ));
        }
        self.queued[index] = false;
        let timestamp = Duration::new(
            b.timestamp.tv_sec.max(0) as u64,
            (b.timestamp.tv_usec.clamp(0, 999_999) as u32) * 1000,
        );
        Ok(Some(Dequeued {
            index,
            bytesused: (b.bytesused as usize).min(self.maps[index].len),
            sequence: b.sequence,
            timestamp,
            flags: b.flags,
        }))
    }
}

impl Drop for MmapQueue {
    fn drop(&mut self) {
        // ENODEV after an unplug is expected; nothing else can be done here either way.
        if self.streaming
            && let Err(e) = self.stream_off()
        {
            tracing::debug!(error = %e, "STREAMOFF on drop failed");
        }
        for m in self.maps.drain(..) {
            // SAFETY: each mapping was created by mmap with this length and is unmapped once.
            if let Err(e) = unsafe { v4l2::munmap(m.ptr as *mut _, m.len) } {
                tracing::warn!(error = %e, "munmap of a V4L2 buffer failed");
            }
        }
        // release the buffers so that the device can be reconfigured by the next user
        // SAFETY: zeroed POD struct passed to the matching ioctl.
        unsafe {
            let mut req: v4l_sys::v4l2_requestbuffers = std::mem::zeroed();
            req.type_ = buf_type(self.dir);
            req.memory = v4l_sys::v4l2_memory_V4L2_MEMORY_MMAP;
            let _ = v4l2::ioctl(
                self.handle.fd(),
                vidioc::VIDIOC_REQBUFS,
                &mut req as *mut _ as *mut _,
            );
        }
    }
}

fn buf_type(dir: Direction) -> u32 {
    match dir {
        Direction::Capture => v4l_sys::v4l2_buf_type_V4L2_BUF_TYPE_VIDEO_CAPTURE,
        Direction::Output => v4l_sys::v4l2_buf_type_V4L2_BUF_TYPE_VIDEO_OUTPUT,
    }
}
