"""The plastic spiking network: input coding -> plastic SRM layers -> output population -> decoder.

One call of :class:`SpikingPlasticNetwork` is one environment step: ``T`` network steps of 1 ms, split into
plasticity intervals of ``plasticity_interval`` steps. The per-environment state (:class:`NetworkState`: every
layer's filters, traces and rule state, plus the input sampler's key) is passed in and returned, never stored.
"""

from __future__ import annotations

from typing import Callable, NamedTuple, Optional, Sequence, Union

import torch
from torch import Tensor, nn

from . import _fast
from .coding import advance_keys, initial_keys
from .compiled_sequence import compiled_sequence_rates
from .compiled_step import compiled_step
from .layers import LayerOutput, LayerState, PlasticSRMLayer, fan_in_std
from .neurons import SRMParameters
from .plasticity import compiled_form, get_rule_class


class NetworkState(NamedTuple):
    """Per-environment state of the whole network (leading batch axis everywhere).

    :param layers: one :class:`~sb3_spikeplastic.snn.layers.LayerState` per layer.
    :param noise_key: ``(batch,)`` int32 key of the replayable input sampler. It is the random stream, not memory:
        it advances every step and is *not* reset at episode starts (otherwise every episode would see the same
        input noise).
    :param source: the state of the policy's modulation source ``(batch, n)`` (e.g. the previous value of a TD
        error, :mod:`sb3_spikeplastic.sb3.modulation`), reset with the layers; ``None`` without one. The network
        passes it on unchanged.
    """

    layers: tuple[LayerState, ...]
    noise_key: Tensor
    source: Optional[Tensor] = None

    def reset(self, episode_start: Tensor, sync_free: bool = False) -> "NetworkState":
        """The state with every environment where ``episode_start`` is 1 set back to its initial value (zeros):
        ``state * (1 - episode_start)``.

        :param sync_free: always multiply, never ask the device whether any episode starts (a host
            synchronisation, which CUDA-graph capture forbids); the values are the same (``x * 1`` is exact).
        """
        episode_start = episode_start.to(self.noise_key.device)
        if not sync_free and not bool(episode_start.any()):
            # Most steps start no episode: skip a pass over every trace-sized tensor (and its autograd node).
            return self
        keep = 1.0 - episode_start.float()

        def zero_where_started(x: Tensor) -> Tensor:
            return x * keep.to(x.dtype).view(-1, *([1] * (x.dim() - 1)))

        return NetworkState(
            map_tensors(zero_where_started, self.layers), self.noise_key, map_tensors(zero_where_started, self.source)
        )

    def select(self, index) -> "NetworkState":
        """The state of the environments ``index`` (anything that indexes the batch axis)."""
        return map_tensors(lambda x: x[index], self)

    def detach(self) -> "NetworkState":
        return map_tensors(torch.Tensor.detach, self)

    def to(self, device) -> "NetworkState":
        return map_tensors(lambda x: x.to(device), self)

    @staticmethod
    def cat(states: Sequence["NetworkState"]) -> "NetworkState":
        """Concatenate states along the batch axis."""
        return zip_tensors(lambda xs: torch.cat(xs, 0), states)

    @staticmethod
    def stack(states: Sequence["NetworkState"]) -> "NetworkState":
        """Stack states on a new leading axis (e.g. chunk snapshots ``(n_chunks, batch, ...)``)."""
        return zip_tensors(lambda xs: torch.stack(xs, 0), states)

    def nbytes(self) -> int:
        """Memory held by the state's tensors."""
        total = 0

        def count(x: Tensor) -> Tensor:
            nonlocal total
            total += x.numel() * x.element_size()
            return x

        map_tensors(count, self)
        return total


def map_tensors(fn: Callable[[Tensor], Tensor], tree):
    """Apply ``fn`` to every tensor of a nest of (named) tuples that may hold ``None``, keeping the structure."""
    if isinstance(tree, Tensor):
        return fn(tree)
    if tree is None:
        return None
    items = [map_tensors(fn, x) for x in tree]
    return type(tree)(*items) if hasattr(tree, "_fields") else type(tree)(items)


def tensor_leaves(tree) -> list[Tensor]:
    """The tensors of a nest, in the order :func:`map_tensors` visits them."""
    leaves: list[Tensor] = []
    map_tensors(lambda x: leaves.append(x) or x, tree)
    return leaves


def zip_tensors(fn: Callable[[list[Tensor]], Tensor], trees: Sequence):
    """Combine same-structured nests leaf by leaf with ``fn`` (a list of tensors -> a tensor)."""
    first = trees[0]
    if isinstance(first, Tensor):
        return fn(list(trees))
    if first is None:
        return None
    items = [zip_tensors(fn, [t[i] for t in trees]) for i in range(len(first))]
    return type(first)(*items) if hasattr(first, "_fields") else type(first)(items)


class NetworkRecord(NamedTuple):
    """Everything the network did during one environment step, for figures (``record=True``).

    :param input_spikes: ``(batch, T, n_in)``.
    :param spikes: per layer ``(batch, T, n)``.
    :param membrane: per layer ``(batch, T, n)``.
    :param modulation: per layer, the neuromodulatory signal of each interval ``(batch, n_intervals, n)`` or ``None``.
    :param traces: per layer, ``E`` after each interval ``(batch, n_intervals, n_out, n_in)`` or ``None``.
    """

    input_spikes: Tensor
    spikes: tuple[Tensor, ...]
    membrane: tuple[Tensor, ...]
    modulation: tuple[Optional[Tensor], ...]
    traces: tuple[Optional[Tensor], ...]


class NetworkOutput(NamedTuple):
    """Result of one environment step.

    :param action: the decoder's output: mean actions (continuous) or logits (discrete), ``(batch, n_actions)``.
    :param rates: per layer (hidden layers, then the output population) the mean spike rate over the step.
    :param record: the full activity when requested, else ``None``.
    :param input_rate: the input population's mean spike rate over the step ``(batch, n_in)`` (for spike and
        synaptic-operation counts, :mod:`sb3_spikeplastic.sb3.activity`).
    :param modulator: the signal from outside the network the step's plasticity read ``(batch, k)``, or ``None``.
    """

    action: Tensor
    rates: tuple[Tensor, ...]
    record: Optional[NetworkRecord]
    input_rate: Optional[Tensor] = None
    modulator: Optional[Tensor] = None


IntOrSeq = Union[float, Sequence[float]]

#: fan-in at which the rules' default ``alpha_init_mean`` was measured (the T-maze's 40 inputs)
ALPHA_REFERENCE_FAN_IN = 40


def _per_layer(value: IntOrSeq, n_layers: int, name: str) -> list[float]:
    if isinstance(value, (int, float)):
        return [float(value)] * n_layers
    values = [float(v) for v in value]
    if len(values) != n_layers:
        raise ValueError(f"{name} needs one value per layer ({n_layers}), got {values}")
    return values


class SpikingPlasticNetwork(nn.Module):
    """Feed-forward SNN with plastic synapses (SpikePropamine): ``encoder -> hidden layers -> output -> decoder``.

    :param encoder: maps ``(obs, keys, T)`` to input spikes ``(batch, T, n_in)``
        (:class:`~sb3_spikeplastic.snn.coding.PopulationEncoder` or :class:`~sb3_spikeplastic.snn.coding.RasterInput`).
    :param decoder: maps output rates ``(batch, n_out)`` to actions or logits.
    :param hidden_sizes: neurons per hidden layer (paper HalfCheetah: ``(64, 64)``).
    :param steps: network steps ``T`` per environment step (1 ms each).
    :param rule: plasticity rule name (see :func:`~sb3_spikeplastic.snn.plasticity.available_rules`).
    :param plastic_layers: indices of the plastic layers (0 = input->first hidden; the last is the output
        layer), or ``"all"``. The others use the ``static`` rule.
    :param neuron: SRM constants shared by all layers.
    :param e_max: trace clip bound.
    :param plasticity_interval: :math:`\\Delta\\tau`, network steps between trace updates; must divide ``steps``
        (default: ``steps``, one update per environment step).
    :param rule_kwargs: extra keyword arguments of the rule class (e.g. ``eta_init``, ``modulation``).
    :param w_init_gain: initial weight spread per layer (or one value for all): the std of ``W`` puts the
        membrane spread at ``gain * theta`` (:func:`~sb3_spikeplastic.snn.layers.fan_in_std`).
    :param w_init_mean: mean of the initial ``W`` per layer (or one value).
    :param alpha_init_mean: mean of the initial ``alpha`` per layer (default: the rule's ``alpha_init_mean``,
        measured on the T-maze's 40-input layer, times ``40 / n_in``: the positive feedback of a positive-mean
        ``alpha`` grows with the number of inputs, and unscaled it drives 600-input layers to saturation).
    :param alpha_init_std: std of the initial ``alpha`` per layer (default: 10% of the mean, as measured).
    :param hidden_rms_rate: assumed rms firing probability of hidden neurons, for the weight init of the layers
        after the first.
    """

    def __init__(
        self,
        encoder: nn.Module,
        decoder: nn.Module,
        hidden_sizes: Sequence[int] = (64, 64),
        steps: int = 50,
        rule: str = "dp-oja",
        plastic_layers: Union[str, Sequence[int]] = "all",
        neuron: SRMParameters = SRMParameters(),
        e_max: float = 1.0,
        plasticity_interval: Optional[int] = None,
        rule_kwargs: Optional[dict] = None,
        w_init_gain: IntOrSeq = 3.0,
        w_init_mean: IntOrSeq = 0.0,
        alpha_init_mean: Optional[IntOrSeq] = None,
        alpha_init_std: Optional[IntOrSeq] = None,
        hidden_rms_rate: float = 0.2,
    ):
        super().__init__()
        if not hidden_sizes or any(isinstance(h, bool) or int(h) != h or h < 1 for h in hidden_sizes):
            raise ValueError(
                f"hidden_sizes={list(hidden_sizes)} must be one or more positive integers (neurons per hidden layer)"
            )
        if steps < 1:
            raise ValueError(f"steps={steps} must be a positive number of network steps T per environment step")
        interval = steps if plasticity_interval is None else int(plasticity_interval)
        if steps < 1 or interval < 1 or steps % interval:
            raise ValueError(f"plasticity_interval={interval} must be a positive divisor of steps T={steps}")
        self.encoder, self.decoder, self.steps, self.interval, self.neuron = (
            encoder,
            decoder,
            int(steps),
            interval,
            neuron,
        )
        sizes = [encoder.n_neurons, *[int(h) for h in hidden_sizes], decoder.n_neurons]
        n_layers = len(sizes) - 1
        if plastic_layers == "all":
            plastic = set(range(n_layers))
        else:
            bad = [i for i in plastic_layers if not -n_layers <= int(i) < n_layers]
            if bad:
                raise ValueError(f"plastic_layers {bad} out of range; accepted: 0..{n_layers - 1} or 'all'")
            plastic = {int(i) % n_layers for i in plastic_layers}
        rule_cls = get_rule_class(rule)
        static_cls = get_rule_class("static")
        gains = _per_layer(w_init_gain, n_layers, "w_init_gain")
        w_means = _per_layer(w_init_mean, n_layers, "w_init_mean")
        if alpha_init_mean is None:
            a_means = [rule_cls.alpha_init_mean * ALPHA_REFERENCE_FAN_IN / n for n in sizes[:-1]]
        else:
            a_means = _per_layer(alpha_init_mean, n_layers, "alpha_init_mean")
        a_stds = (
            [0.1 * abs(m) for m in a_means]
            if alpha_init_std is None
            else _per_layer(alpha_init_std, n_layers, "alpha_init_std")
        )
        layers = []
        for i, (n_in, n_out) in enumerate(zip(sizes[:-1], sizes[1:])):
            cls = rule_cls if i in plastic else static_cls
            try:
                layer_rule = cls(n_in, n_out, e_max=e_max, **(rule_kwargs or {})) if cls.has_trace else cls(n_in, n_out)
            except TypeError as exc:
                raise ValueError(f"bad rule_kwargs {rule_kwargs!r} for rule {cls.name!r}: {exc}") from None
            rms = encoder.rms_rate() if i == 0 else hidden_rms_rate
            layers.append(
                PlasticSRMLayer(
                    n_in,
                    n_out,
                    layer_rule,
                    neuron,
                    w_means[i],
                    fan_in_std(n_in, rms, neuron, gains[i]),
                    a_means[i],
                    a_stds[i],
                )
            )
        self.layers = nn.ModuleList(layers)
        self.rule_name = rule
        # Per layer, whether its rule reads the modulator: looked up once, not on every interval of every step.
        self._reads_modulator = tuple(layer.plastic and layer.rule.takes_modulator for layer in layers)
        self._modulator_channels = max(
            (layer.rule.modulator_gains.shape[1] for layer, reads in zip(layers, self._reads_modulator) if reads),
            default=0,
        )

    @property
    def sizes(self) -> list[int]:
        return [self.layers[0].n_in] + [layer.n_out for layer in self.layers]

    @property
    def modulator_channels(self) -> int:
        """Channels of the signal from outside the network that the plastic layers' rules read on every step (the
        ``modulator`` of :meth:`forward`); 0 where every rule forms its modulation itself."""
        return self._modulator_channels

    def backward_bytes_per_step(self, dtype: torch.dtype = torch.float32) -> int:
        """Memory that backpropagation keeps per environment step of one sequence with the compiled CPU ops (which
        ``chunks_per_pass="auto"`` sizes its passes for; the eager ops keep more), estimated from the sizes: per
        layer and interval, the trace ``E`` (plastic layers; every other one where the compiled ops defer the
        built-in rules' updates, see :meth:`forward_sequence`), the ``L + 2`` rows its product reads (the spikes and
        the carried PSP state, filtered or not), its surrogate gradient ``(L, n_out)``, both rates and the rule's
        terms (``n_in + 2 n_out`` values)."""
        deferred = _fast.interval_ops() is not None
        per_interval = 0.0
        for layer in self.layers:
            per_interval += (self.interval + 3) * layer.n_in + (self.interval + 1) * layer.n_out
            if layer.plastic:
                half = deferred and compiled_form(layer.rule) is not None
                per_interval += layer.n_out * layer.n_in / (2 if half else 1) + layer.n_in + 2 * layer.n_out
        return int(per_interval * (self.steps // self.interval) * torch.empty(0, dtype=dtype).element_size())

    def initial_state(self, batch: int, seed: int = 0, device=None, dtype: torch.dtype = torch.float32) -> NetworkState:
        """Initial state of ``batch`` environments; ``seed`` picks the input-noise streams."""
        device = device if device is not None else self.layers[0].weight.device
        return NetworkState(
            tuple(layer.initial_state(batch, dtype, device) for layer in self.layers), initial_keys(batch, seed, device)
        )

    def forward(
        self,
        obs: Tensor,
        state: NetworkState,
        record: bool = False,
        defer_updates: bool = False,
        hold_plastic: bool = False,
        modulator: Optional[Tensor] = None,
    ) -> tuple[NetworkOutput, NetworkState]:
        """One environment step for a batch of observations; returns ``(output, new_state)``.

        With ``defer_updates`` the built-in rules' last trace updates stay pending in the returned state (the next
        step applies them in its own pass over the traces; :meth:`settle` applies them), as
        :meth:`forward_sequence` runs its steps. With ``hold_plastic`` every layer keeps the plastic state it came
        in with (traces, rule state): its updates are dropped, also between the intervals of the step (the
        ``frozen`` ablation, :mod:`sb3_spikeplastic.sb3.ablation`). ``modulator`` ``(batch, k)``: the signal from
        outside the network that rules with an external ``modulation_source`` read at every update of the step
        (:attr:`modulator_channels`; required exactly where they are)."""
        self._check_modulator(modulator, obs.shape[0])
        spikes_in = self.encoder(obs, state.noise_key, self.steps)
        if not record and not defer_updates:
            compiled = compiled_step(self, spikes_in, state.layers, hold_plastic)
            if compiled is not None:
                rates, input_rate, layer_states = compiled
                new_state = NetworkState(layer_states, advance_keys(state.noise_key), state.source)
                return NetworkOutput(self.decoder(rates[-1]), rates, None, input_rate, modulator), new_state
        layer_states = list(state.layers)
        n_intervals = self.steps // self.interval
        outputs: list[list[LayerOutput]] = [[] for _ in self.layers]
        traces: list[list[Tensor]] = [[] for _ in self.layers]
        for j in range(n_intervals):
            x = spikes_in if n_intervals == 1 else spikes_in[:, j * self.interval : (j + 1) * self.interval]
            for i, (layer, reads) in enumerate(zip(self.layers, self._reads_modulator)):
                out, layer_states[i] = layer(x, layer_states[i], record, defer_updates, modulator if reads else None)
                if hold_plastic and layer.plastic:
                    layer_states[i] = layer_states[i]._replace(plastic=state.layers[i].plastic)
                outputs[i].append(out)
                if record and layer.plastic:
                    traces[i].append(layer_states[i].plastic.trace)
                x = out.spikes
        spikes = [outs[0].spikes if n_intervals == 1 else torch.cat([o.spikes for o in outs], 1) for outs in outputs]
        if n_intervals == 1:  # the layers' own rates (the same op on the same spikes)
            rates = tuple(outs[0].rate for outs in outputs)
            input_rate = outputs[0][0].input_rate
        else:
            rates = tuple(s.mean(1) for s in spikes)
            input_rate = spikes_in.mean(1)
        new_state = NetworkState(tuple(layer_states), advance_keys(state.noise_key), state.source)
        rec = None
        if record:
            rec = NetworkRecord(
                spikes_in,
                tuple(spikes),
                tuple(torch.cat([o.membrane for o in outs], 1) for outs in outputs),
                tuple(
                    torch.stack([o.modulation for o in outs], 1) if outs[0].modulation is not None else None
                    for outs in outputs
                ),
                tuple(torch.stack(t, 1) if t else None for t in traces),
            )
        return NetworkOutput(self.decoder(rates[-1]), rates, rec, input_rate, modulator), new_state

    def _check_modulator(self, modulator: Optional[Tensor], batch: int) -> None:
        channels = self.modulator_channels
        if channels == 0 and modulator is not None:
            raise ValueError(
                "a modulator was passed, but no plastic layer's rule takes one (modulation_source='learned')"
            )
        if channels and (modulator is None or tuple(modulator.shape) != (batch, channels)):
            got = None if modulator is None else tuple(modulator.shape)
            raise ValueError(
                f"the plastic layers' rules read a modulator of shape (batch, channels) = ({batch}, {channels}) from "
                f"outside the network on every step; got {got}"
            )

    def forward_sequence(
        self,
        obs: Tensor,
        episode_start: Tensor,
        state: NetworkState,
        sync_free: bool = False,
        modulators: Optional[Tensor] = None,
        final_state: bool = True,
    ) -> tuple[list[NetworkOutput], Optional[NetworkState]]:
        """Run a sequence ``obs`` of shape ``(L, batch, ...)`` from ``state``, resetting where ``episode_start``
        ``(L, batch)`` is 1 (truncated BPTT through the whole sequence, traces included); ``sync_free`` as in
        :meth:`NetworkState.reset`. The steps defer the trace updates to the next step (``defer_updates``): one
        pass over each trace fewer, forward and backward; the returned state has them applied. ``modulators``
        ``(L, batch, k)``: each step's ``modulator`` (see :meth:`forward`). Without ``final_state`` the state is not
        returned (``None``), and where it applies the whole sequence runs as one autograd node
        (:mod:`sb3_spikeplastic.snn.compiled_sequence`: the same outputs and gradients, less overhead)."""
        if not final_state and modulators is None:
            outputs = self._compiled_sequence(obs, episode_start, state)
            if outputs is not None:
                return outputs, None
        outputs = []
        for k in range(obs.shape[0]):
            modulator = None if modulators is None else modulators[k]
            out, state = self(obs[k], state.reset(episode_start[k], sync_free), defer_updates=True, modulator=modulator)
            outputs.append(out)
        return outputs, self.settle(state) if final_state else None

    def _compiled_sequence(
        self, obs: Tensor, episode_start: Tensor, state: NetworkState
    ) -> Optional[list[NetworkOutput]]:
        """:meth:`forward_sequence`'s outputs by
        :func:`~sb3_spikeplastic.snn.compiled_sequence.compiled_sequence_rates`, or ``None`` where it does not apply."""
        if not torch.is_grad_enabled() or self.modulator_channels:
            return None
        keys, spikes = state.noise_key, []
        for k in range(obs.shape[0]):
            spikes.append(self.encoder(obs[k], keys, self.steps))
            keys = advance_keys(keys)
        result = compiled_sequence_rates(self, spikes, episode_start, state)
        if result is None:
            return None
        rates, input_rates = result
        return [NetworkOutput(self.decoder(r[-1]), r, None, i) for r, i in zip(rates, input_rates)]

    def settle(self, state: NetworkState) -> NetworkState:
        """``state`` with every layer's pending trace update applied (see :meth:`forward`)."""
        layers = tuple(
            s._replace(plastic=layer.rule.apply_pending(s.plastic)) if s.plastic.pending is not None else s
            for layer, s in zip(self.layers, state.layers)
        )
        return state._replace(layers=layers)
