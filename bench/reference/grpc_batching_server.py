#!/usr/bin/env python3
"""A dynamic-batching Python gRPC server for relreward.v1 RewardService.Gradient and
GradientStream: the strongest Python peer of the serving benchmark (tests/bench/serving.sh),
written the way a competent engineer would serve a small PyTorch model today.

    .venv/bin/python bench/reference/grpc_batching_server.py --models-dir MODELS --model maze-reward

Same models, weights, request checks and numbers as bench/reference/grpc_server.py (it
imports that file's loading and `make_request_handling`), served differently:

- grpc.aio (asyncio): one event loop holds every call and stream; no thread per stream.
- One batching queue per model: a request is decoded and checked on the event loop, then
  queued with a future. The model's batcher task takes the first queued request, waits up to
  `--max-delay-ms` (default 0: whatever is queued now) for more, up to `--max-batch` items,
  concatenates them and runs ONE forward/backward pass on a dedicated compute thread (so the
  event loop keeps accepting and decoding while torch computes; torch releases the GIL in
  its kernels), then splits the results back to each request's future. Requests that arrive
  while a pass runs form the next batch: under load, batches grow by themselves.
- GradientStream reads requests as they come and answers each as soon as its batch is done
  (matched by request_id), so one stream's requests share passes with everyone else's; a bad
  request gets its `error` in its response and the stream goes on.
- A full queue (`--queue-capacity` items waiting) answers RESOURCE_EXHAUSTED at once instead
  of letting latency grow without bound.

Prints `reference grpc_batching_server listening on HOST:PORT` as its first stdout line.
"""

import argparse
import asyncio
import signal
import sys
from concurrent import futures

import torch

# The sibling script (this folder is sys.path[0] when a script here runs).
from grpc_server import BadRequest, add_model_flags, announce, load_stubs, make_request_handling, models_from_flags


class Batcher:
    """One model's queue and batching loop."""

    def __init__(self, model, compute, executor, max_batch, max_delay_s, capacity):
        self.model = model
        self.compute = compute
        self.executor = executor
        self.max_batch = max_batch
        self.max_delay_s = max_delay_s
        self.capacity = capacity
        self.queue = asyncio.Queue()
        self.waiting_items = 0
        self.task = None

    def start(self):
        self.task = asyncio.get_running_loop().create_task(self.run())

    async def submit(self, x, t):
        """(rho, grad) for this request's items, computed in some batch."""
        b = x.shape[0]
        if self.waiting_items + b > self.capacity:
            raise BadRequest("RESOURCE_EXHAUSTED", f"model '{self.model.name}': queue full, retry later")
        future = asyncio.get_running_loop().create_future()
        self.waiting_items += b
        self.queue.put_nowait((x, t, future))
        return await future

    async def run(self):
        loop = asyncio.get_running_loop()
        while True:
            first = await self.queue.get()
            batch, items = [first], first[0].shape[0]
            deadline = loop.time() + self.max_delay_s
            while items < self.max_batch:
                if not self.queue.empty():
                    nxt = self.queue.get_nowait()
                else:
                    remaining = deadline - loop.time()
                    if remaining <= 0:
                        break
                    try:
                        nxt = await asyncio.wait_for(self.queue.get(), remaining)
                    except asyncio.TimeoutError:
                        break
                batch.append(nxt)
                items += nxt[0].shape[0]
            self.waiting_items -= items
            live = [entry for entry in batch if not entry[2].cancelled()]  # callers gone: skip
            if not live:
                continue
            x = torch.cat([entry[0] for entry in live])
            t = torch.cat([entry[1] for entry in live])
            try:
                rho, grad = await loop.run_in_executor(self.executor, self.compute, self.model, x, t)
            except Exception as e:  # noqa: BLE001 - every waiter must hear about it
                for entry in live:
                    if not entry[2].done():
                        entry[2].set_exception(e)
                continue
            sizes = [entry[0].shape[0] for entry in live]
            for entry, r, g in zip(live, rho.split(sizes), grad.split(sizes)):
                if not entry[2].done():
                    entry[2].set_result((r, g))


def make_servicer(models, batchers, prepare, finish, reward_pb2, reward_pb2_grpc):
    import grpc

    async def answer(request):
        model, x, t, omega, raw_grad = prepare(request)
        rho, grad = await batchers[model.name].submit(x, t)
        return finish(request, model, rho, grad, omega, raw_grad)

    class Servicer(reward_pb2_grpc.RewardServiceServicer):
        async def Gradient(self, request, context):
            try:
                return await answer(request)
            except BadRequest as e:
                await context.abort(getattr(grpc.StatusCode, e.code), str(e))

        async def GradientStream(self, request_iterator, context):
            out = asyncio.Queue()

            async def one(request):
                try:
                    await out.put(await answer(request))
                except BadRequest as e:
                    code = getattr(grpc.StatusCode, e.code).value[0]
                    await out.put(
                        reward_pb2.GradientResponse(
                            request_id=request.request_id, error=reward_pb2.StreamError(code=code, message=str(e))
                        )
                    )

            pending = set()

            async def read():
                async for request in request_iterator:
                    task = asyncio.get_running_loop().create_task(one(request))
                    pending.add(task)
                    task.add_done_callback(pending.discard)
                if pending:
                    await asyncio.gather(*list(pending))
                await out.put(None)

            reader = asyncio.get_running_loop().create_task(read())
            try:
                while (response := await out.get()) is not None:
                    yield response
            finally:
                reader.cancel()
                for task in list(pending):
                    task.cancel()

    return Servicer()


async def serve(args, models, reward_pb2, reward_pb2_grpc, tensor_pb2):
    import grpc

    prepare, compute, finish = make_request_handling(models, reward_pb2, tensor_pb2)
    # One compute thread: passes run one at a time (as relreward's one serving thread per
    # model), the event loop stays free for decoding and answering.
    executor = futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="compute")
    batchers = {
        name: Batcher(m, compute, executor, args.max_batch, args.max_delay_ms / 1000.0, args.queue_capacity)
        for name, m in models.items()
    }
    for b in batchers.values():
        b.start()
    server = grpc.aio.server(
        options=[("grpc.max_receive_message_length", 16 << 20), ("grpc.max_send_message_length", 16 << 20)],
    )
    reward_pb2_grpc.add_RewardServiceServicer_to_server(
        make_servicer(models, batchers, prepare, finish, reward_pb2, reward_pb2_grpc), server
    )
    port = server.add_insecure_port(args.listen)
    if port == 0:
        sys.exit(f"grpc_batching_server.py: cannot listen on {args.listen}")
    await server.start()
    announce("grpc_batching_server", args.listen, port, models,
             f"max_batch {args.max_batch}, max_delay_ms {args.max_delay_ms}")
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    await stop.wait()
    await server.stop(grace=1)
    executor.shutdown(wait=False, cancel_futures=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_model_flags(ap)
    ap.add_argument("--max-batch", type=int, default=256, help="most items per pass (relreward's default)")
    ap.add_argument("--max-delay-ms", type=float, default=0.0, help="wait for company after the first request")
    ap.add_argument("--queue-capacity", type=int, default=4096, help="items waiting per model before refusing")
    args = ap.parse_args()
    if args.max_batch < 1 or args.max_delay_ms < 0 or args.queue_capacity < 1:
        ap.error("--max-batch and --queue-capacity must be positive, --max-delay-ms at least 0")
    models = models_from_flags(ap, args)
    reward_pb2, reward_pb2_grpc, tensor_pb2 = load_stubs()
    asyncio.run(serve(args, models, reward_pb2, reward_pb2_grpc, tensor_pb2))


if __name__ == "__main__":
    main()
