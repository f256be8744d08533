//! A thread fed through a bounded queue, for work the render thread hands off and never waits
//! for (probe brackets, image writes): offering never blocks, a full queue hands the item back,
//! and dropping the worker lets it finish what is queued, then joins it.

use std::thread::JoinHandle;

use crossbeam_channel::{Sender, TrySendError, bounded};

pub struct Worker<T> {
    name: &'static str,
    input: Option<Sender<T>>,
    thread: Option<JoinHandle<()>>,
}

impl<T> std::fmt::Debug for Worker<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Worker")
            .field("name", &self.name)
            .field("queued", &self.input.as_ref().map(Sender::len))
            .finish_non_exhaustive()
    }
}

impl<T: Send + 'static> Worker<T> {
    /// A thread called `name` that runs `handle` on every item, `capacity` of them queued.
    pub fn spawn(
        name: &'static str,
        capacity: usize,
        mut handle: impl FnMut(T) + Send + 'static,
    ) -> std::io::Result<Self> {
        let (input, items) = bounded(capacity);
        let thread = std::thread::Builder::new()
            .name(name.into())
            .spawn(move || items.into_iter().for_each(&mut handle))?;
        Ok(Self {
            name,
            input: Some(input),
            thread: Some(thread),
        })
    }

    /// Queue `item` without waiting; `Err` hands it back when the queue is full (or the thread
    /// has ended).
    pub fn offer(&self, item: T) -> Result<(), T> {
        match self.input.as_ref().map(|input| input.try_send(item)) {
            Some(Ok(())) => Ok(()),
            Some(Err(TrySendError::Full(item) | TrySendError::Disconnected(item))) => Err(item),
            None => Ok(()),
        }
    }
}

impl<T> Drop for Worker<T> {
    fn drop(&mut self) {
        self.input = None;
        if let Some(thread) = self.thread.take()
            && thread.join().is_err()
        {
            tracing::error!(thread = self.name, "worker thread panicked");
        }
    }
}
